// One build variant of the kernel (see setup.py): a separate file so each variant gets its own object file.
#include "raster.cpp"
