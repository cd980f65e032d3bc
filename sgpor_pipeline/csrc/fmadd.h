// fmadd(): the fused multiply-adds of raster.h and ssim.h (match.h lets gcc fuse its one; see there).
#pragma once

#include <cmath>

namespace sgpor {

// a * b + c, fused into one rounding where the target has FMA (x86-64-v3 and v4, aarch64); a multiply
// and an add where it has not (x86-64-v2). The kernel is built with -ffp-contract=off, so these are
// the only multiply-adds that fuse: with gcc free to fuse (-ffp-contract=fast), which products it
// fused depended on the vector width and on the code around the expression, and the AVX2 and
// AVX-512 builds came to round differently (seen on a lent machine's Xeon after an unrelated change
// to the backward). Written out, every FMA build computes the same operations in every lane.
template <typename T>
inline T fmadd(T a, T b, T c) {
#if defined(__FMA__) || defined(__ARM_FEATURE_FMA)
  return std::fma(a, b, c);
#else
  return a * b + c;
#endif
}

}  // namespace sgpor
