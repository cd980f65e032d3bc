"""Builds the C++ rasterizer kernel (plain C++17, no torch headers; loaded with ctypes).

Everything else about the package lives in pyproject.toml.
"""

from setuptools import setup

setup()
