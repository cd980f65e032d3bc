"""Builds the C++ rasterizer kernel (plain C++17, no torch headers; loaded with ctypes).

Everything else about the package lives in pyproject.toml.

The kernel (``sgpor_pipeline/csrc/raster.cpp``) is compiled once per x86-64 micro-architecture
level (``x86-64-v2``: SSE4.2, ``-v3``: AVX2+FMA, ``-v4``: AVX-512) into
``sgpor_pipeline/_raster_kernel_<level>*.so``; at run time the loader picks the best level the CPU
supports, so a wheel stays portable. The builds with FMA (v3, v4) give bitwise the same results
(SIMD lanes are summed in a fixed tree, not in the vector width's order, and the kernel is built
with ``-ffp-contract=off``: the multiply-adds that fuse are written out, ``csrc/fmadd.h``; tested
where a CPU runs both), so AVX2 and AVX-512 machines get the same renders and gradients; v2 has no
FMA and rounds those multiply-adds differently. Other architectures get one generic build.
Environment:

* ``SGPOR_KERNEL_NATIVE=1`` adds a ``-march=native`` build, preferred at run time (not portable).
* ``SGPOR_KERNEL_LEVELS=v3,v4`` restricts the x86-64 levels built (default: all three).
* ``SGPOR_NO_KERNEL=1`` builds no kernel (the rasterizer then falls back to slow pure PyTorch).

A failed kernel build does not fail the install (the extensions are optional): the rasterizer
warns once at run time and uses the PyTorch reference.
"""

import os
import platform

from setuptools import Extension, setup
from setuptools.command.build_ext import build_ext

# Exactly the flags DESIGN.md section 6 verified; never -ffast-math (it would change the
# floating-point environment of the whole Python process through crtfastmath.o).
COMMON_FLAGS = [
    "-O3",
    "-std=c++17",
    "-fopenmp",
    "-fno-trapping-math",
    "-fno-math-errno",
    "-ffinite-math-only",
    "-fno-signed-zeros",
    "-ffp-contract=off",  # the multiply-adds that fuse are written out: csrc/fmadd.h
    "-fvisibility=hidden",
    "-DNDEBUG",
    "-g0",
]
CSRC = "sgpor_pipeline/csrc"
DEPENDS = [f"{CSRC}/{name}" for name in ("raster.h", "ssim.h", "match.h", "fmadd.h", "raster.cpp")]


def _kernel(suffix: str, march: list[str]) -> Extension:
    return Extension(
        f"sgpor_pipeline._raster_kernel_{suffix}",
        # one stub source per variant (it includes raster.cpp), so that parallel builds of the
        # variants never share an object file
        sources=[f"{CSRC}/kernel_{suffix}.cpp"],
        depends=DEPENDS,
        language="c++",
        extra_compile_args=COMMON_FLAGS + march,
        extra_link_args=["-fopenmp"],
        optional=True,
    )


def _extensions() -> list[Extension]:
    if os.environ.get("SGPOR_NO_KERNEL", "") not in ("", "0"):
        return []
    exts = []
    machine = platform.machine().lower()
    if machine in ("x86_64", "amd64"):
        wanted = os.environ.get("SGPOR_KERNEL_LEVELS", "v2,v3,v4")
        for level in [w.strip() for w in wanted.split(",") if w.strip()]:
            exts.append(_kernel(f"x86_64_{level}", [f"-march=x86-64-{level}", "-mtune=generic"]))
    else:
        exts.append(_kernel("generic", []))
    if os.environ.get("SGPOR_KERNEL_NATIVE", "") not in ("", "0"):
        exts.append(_kernel("native", ["-march=native"]))
    return exts


class BuildExt(build_ext):
    """Compiles the kernel variants in parallel; replaces (never rewrites) an installed library."""

    def finalize_options(self) -> None:
        super().finalize_options()
        if not self.parallel:
            self.parallel = os.cpu_count() or 1

    def copy_file(self, infile, outfile, *args, **kwargs):
        # A running process may have the old library mapped: writing into that file (what a plain
        # copy does) can crash it. Unlinking first leaves the old inode to the running process.
        if isinstance(outfile, str) and outfile.endswith(".so") and os.path.isfile(outfile):
            os.unlink(outfile)
        return super().copy_file(infile, outfile, *args, **kwargs)


setup(ext_modules=_extensions(), cmdclass={"build_ext": BuildExt})
