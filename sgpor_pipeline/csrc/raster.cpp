// C ABI of the CPU rasterizer (loaded with ctypes by sgpor_pipeline/gaussians/_raster_cpu.py).
//
// Every function exists for float ("_f32") and double ("_f64"); arrays are contiguous, row-major,
// with the shapes given in raster.h. Scalars that are floating point are passed as double.
#include "raster.h"
#include "ssim.h"
#include "match.h"

using namespace sgpor;

namespace {

template <typename T, int TS, int CH>
void fwd_impl(int C, int N, int W, int H, const T* means2d, const T* conics, const T* feats,
              const T* opac, const int32_t* rect, const int64_t* tile_off, const Isect* isect,
              const int64_t* goff, const uint8_t* cmask, T* out, T* alpha,
              T* tfinal, int32_t* last, T* contrib, void* packed, int nthreads) {
  // the packed Gaussians are kept by the caller for the backward
  GaussPix<T, CH>* gp = static_cast<GaussPix<T, CH>*>(packed);
  pack_gaussians<T, CH>(C, N, means2d, conics, feats, opac, rect, gp, nthreads);
  raster_fwd<T, TS, CH>(C, N, W, H, gp, tile_off, isect, goff, cmask, out, alpha, tfinal, last,
                        contrib, nthreads);
}

// The median depth (raster_fwd's MED) of Gaussians whose single feature is their depth; the
// other outputs of the pass are scratch.
template <typename T, int TS>
void median_impl(int C, int N, int W, int H, const T* means2d, const T* conics, const T* depths,
                 const T* opac, const int32_t* rect, const int64_t* tile_off, const Isect* isect,
                 const int64_t* goff, const uint8_t* cmask, T* median, T* alpha, T* contrib,
                 int nthreads) {
  const int64_t pixels = std::max<int64_t>(int64_t(C) * H * W, 1);
  std::unique_ptr<GaussPix<T, 1>[]> gp(new GaussPix<T, 1>[std::max<int64_t>(int64_t(C) * N, 1)]);
  std::unique_ptr<T[]> out(new T[pixels]), tfinal(new T[pixels]);
  std::unique_ptr<int32_t[]> last(new int32_t[pixels]);
  pack_gaussians<T, 1>(C, N, means2d, conics, depths, opac, rect, gp.get(), nthreads);
  raster_fwd<T, TS, 1, true>(C, N, W, H, gp.get(), tile_off, isect, goff, cmask, out.get(), alpha,
                             tfinal.get(), last.get(), contrib, nthreads, median);
}

template <typename T, int TS, int CH>
void bwd_impl(int C, int N, int W, int H, const void* packed, const int64_t* tile_off,
              const Isect* isect, const int64_t* goff, const T* tfinal,
              const int32_t* last, const T* g_out, const T* g_alpha, T* g_means2d, T* g_conics,
              T* g_feats, T* g_opac, const uint8_t* train, int nthreads) {
  const GaussPix<T, CH>* gp = static_cast<const GaussPix<T, CH>*>(packed);
  raster_bwd<T, TS, CH>(C, N, W, H, gp, tile_off, isect, goff, tfinal, last, g_out, g_alpha,
                        g_means2d, g_conics, g_feats, g_opac, nthreads, train);
}

template <typename T, int TS>
int fwd_ch(int CH, int C, int N, int W, int H, const T* m2, const T* con, const T* f, const T* o,
           const int32_t* rect, const int64_t* to, const Isect* isect, const int64_t* goff, const uint8_t* cm, T* out, T* al, T* tf, int32_t* last, T* contrib,
           void* pk, int nt) {
  switch (CH) {
    case 1: fwd_impl<T, TS, 1>(C, N, W, H, m2, con, f, o, rect, to, isect, goff, cm, out, al, tf, last, contrib, pk, nt); return 0;
    case 2: fwd_impl<T, TS, 2>(C, N, W, H, m2, con, f, o, rect, to, isect, goff, cm, out, al, tf, last, contrib, pk, nt); return 0;
    case 3: fwd_impl<T, TS, 3>(C, N, W, H, m2, con, f, o, rect, to, isect, goff, cm, out, al, tf, last, contrib, pk, nt); return 0;
    case 4: fwd_impl<T, TS, 4>(C, N, W, H, m2, con, f, o, rect, to, isect, goff, cm, out, al, tf, last, contrib, pk, nt); return 0;
    default: return -1;
  }
}

template <typename T, int TS>
int bwd_ch(int CH, int C, int N, int W, int H, const void* pk, const int64_t* to,
           const Isect* isect, const int64_t* goff, const T* tf,
           const int32_t* last, const T* go, const T* ga, T* gm2, T* gcon, T* gf, T* gop,
           const uint8_t* tr, int nt) {
  switch (CH) {
    case 1: bwd_impl<T, TS, 1>(C, N, W, H, pk, to, isect, goff, tf, last, go, ga, gm2, gcon, gf, gop, tr, nt); return 0;
    case 2: bwd_impl<T, TS, 2>(C, N, W, H, pk, to, isect, goff, tf, last, go, ga, gm2, gcon, gf, gop, tr, nt); return 0;
    case 3: bwd_impl<T, TS, 3>(C, N, W, H, pk, to, isect, goff, tf, last, go, ga, gm2, gcon, gf, gop, tr, nt); return 0;
    case 4: bwd_impl<T, TS, 4>(C, N, W, H, pk, to, isect, goff, tf, last, go, ga, gm2, gcon, gf, gop, tr, nt); return 0;
    default: return -1;
  }
}

}  // namespace

#define SGPOR_API extern "C" __attribute__((visibility("default")))

SGPOR_API int sgpor_abi_version() { return 8; }  // 3: sgpor_ssim_fwd / _bwd; 4: SH in two row arrays; 5: masked_ssd; 7: raster_bwd train mask
// 6: masked_ssd_u8; 8: masked_ssd's shift step

SGPOR_API int sgpor_cpu_level() {
#if defined(__x86_64__) || defined(__i386__)
  __builtin_cpu_init();
  if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
      __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512dq") &&
      __builtin_cpu_supports("avx512cd") && __builtin_cpu_supports("avx2") &&
      __builtin_cpu_supports("fma") && __builtin_cpu_supports("bmi2"))
    return 4;
  if (__builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") &&
      __builtin_cpu_supports("bmi2") && __builtin_cpu_supports("f16c"))
    return 3;
  if (__builtin_cpu_supports("sse4.2") && __builtin_cpu_supports("popcnt")) return 2;
  return 1;
#else
  return 0;
#endif
}

SGPOR_API void sgpor_last_stats(int64_t* out) {
  for (int i = 0; i < 4; ++i) out[i] = stats_slots()[i];
}

// Number of NaN/inf values (exponent bits all ones), by integer bit tests: the kernel is built
// with -ffinite-math-only, under which std::isfinite may be folded to true. The trainer scans every
// parameter and gradient each iteration (13 tensors; SH coefficients: 48 values per Gaussian), so
// both branches must be vectorised: the serial branch of "parallel for simd ... if()" is not (GCC:
// 1M floats took 0.7 ms, 10x a torch.sum of them, a tenth of a fit's iteration in all). Threaded
// from 256k values (a parallel region costs a few microseconds). Integer counts: the result does not
// depend on the thread count.
constexpr int64_t kParallelScan = int64_t(1) << 18;
template <typename U>
int64_t scan_nonfinite(const U* x, int64_t n, U exponent) {
  int64_t bad = 0;
  if (n >= kParallelScan) {
#pragma omp parallel for simd reduction(+ : bad) schedule(static)
    for (int64_t i = 0; i < n; ++i) bad += (x[i] & exponent) == exponent;
  } else {
#pragma omp simd reduction(+ : bad)
    for (int64_t i = 0; i < n; ++i) bad += (x[i] & exponent) == exponent;
  }
  return bad;
}
SGPOR_API int64_t sgpor_count_nonfinite_f32(const uint32_t* x, int64_t n) {
  return scan_nonfinite(x, n, uint32_t(0x7f800000u));
}
SGPOR_API int64_t sgpor_count_nonfinite_f64(const uint64_t* x, int64_t n) {
  return scan_nonfinite(x, n, uint64_t(0x7ff0000000000000ull));
}

SGPOR_API int sgpor_max_threads() {
#ifdef _OPENMP
  return omp_get_max_threads();
#else
  return 1;
#endif
}

#define SGPOR_DEFINE(T, SUF)                                                                        \
  SGPOR_API int64_t sgpor_project_fwd_##SUF(                                                        \
      int C, int N, const T* means, const T* quats, const T* scales, const T* opac,                \
      const T* viewmats, const T* Ks, int W, int H, double near, double far, double eps2d,         \
      int tile, T* means2d, T* conics, T* depths, int32_t* radii, int32_t* rect, int32_t* ntiles,  \
      int nthreads) {                                                                               \
    return project_fwd<T>(C, N, means, quats, scales, opac, viewmats, Ks, W, H, T(near), T(far),   \
                          T(eps2d), tile, means2d, conics, depths, radii, rect, ntiles, nthreads); \
  }                                                                                                 \
  SGPOR_API void sgpor_project_bwd_##SUF(                                                           \
      int C, int N, const T* means, const T* quats, const T* scales, const T* viewmats,            \
      const T* Ks, int W, int H, double near, double far, double eps2d, const int32_t* radii,      \
      const T* g_means2d, const T* g_conics, const T* g_depths, T* g_means, T* g_quats,            \
      T* g_scales, int nthreads) {                                                                  \
    project_bwd<T>(C, N, means, quats, scales, viewmats, Ks, W, H, T(near), T(far), T(eps2d),      \
                   radii, g_means2d, g_conics, g_depths, g_means, g_quats, g_scales, nthreads);     \
  }                                                                                                 \
  SGPOR_API void sgpor_sh_fwd_##SUF(int C, int N, int KN, int deg, const T* means, const T* sh0,    \
                                    int64_t stride0, const T* shN, int64_t strideN,              \
                                    const T* viewmats, T* rgb, int nthreads) {                      \
    sh_fwd<T>(C, N, deg, means, ShRows<T>{sh0, stride0, shN, strideN, KN}, viewmats, rgb,          \
              nthreads);                                                                            \
  }                                                                                                 \
  SGPOR_API void sgpor_sh_bwd_##SUF(int C, int N, int KN, int deg, const T* means, const T* sh0,    \
                                    int64_t stride0, const T* shN, int64_t strideN,              \
                                    const T* viewmats, const T* g_rgb, T* g_means, T* g_sh0,       \
                                    int64_t gstride0, T* g_shN, int64_t gstrideN, int nthreads) {   \
    sh_bwd<T>(C, N, deg, means, ShRows<T>{sh0, stride0, shN, strideN, KN}, viewmats, g_rgb,        \
              g_means, ShRowsOf<T*>{g_sh0, gstride0, g_shN, gstrideN, KN}, nthreads);               \
  }                                                                                                 \
  SGPOR_API void sgpor_bin_##SUF(int C, int N, int W, int H, int tile, const T* depths,            \
                                 const int32_t* rect, const int32_t* ntiles, int64_t* tile_off,     \
                                 Isect* isect, int64_t* gauss_off,                                  \
                                 int nthreads) {                                                    \
    bin<T>(C, N, W, H, tile, depths, rect, ntiles, tile_off, isect, gauss_off, nthreads);           \
  }                                                                                                 \
  SGPOR_API int sgpor_raster_fwd_##SUF(                                                             \
      int C, int N, int CH, int W, int H, int tile, const T* means2d, const T* conics,              \
      const T* feats, const T* opac, const int32_t* rect, const int64_t* tile_off,                  \
      const Isect* isect, const int64_t* goff, const uint8_t* cmask, T* out,                        \
      T* alpha, T* tfinal, int32_t* last, T* contrib, void* packed, int nthreads) {                 \
    if (tile == 8)                                                                                  \
      return fwd_ch<T, 8>(CH, C, N, W, H, means2d, conics, feats, opac, rect, tile_off, isect,   \
                          goff, cmask, out, alpha, tfinal, last, contrib, packed, nthreads);        \
    if (tile == 16)                                                                                 \
      return fwd_ch<T, 16>(CH, C, N, W, H, means2d, conics, feats, opac, rect, tile_off, isect,  \
                           goff, cmask, out, alpha, tfinal, last, contrib, packed, nthreads);       \
    return -2;                                                                                      \
  }                                                                                                 \
  SGPOR_API int sgpor_raster_median_##SUF(                                                          \
      int C, int N, int W, int H, int tile, const T* means2d, const T* conics, const T* depths,     \
      const T* opac, const int32_t* rect, const int64_t* tile_off, const Isect* isect,              \
      const int64_t* goff, const uint8_t* cmask, T* median, T* alpha, T* contrib, int nthreads) {   \
    if (tile == 8)                                                                                  \
      median_impl<T, 8>(C, N, W, H, means2d, conics, depths, opac, rect, tile_off, isect, goff,    \
                        cmask, median, alpha, contrib, nthreads);                                   \
    else if (tile == 16)                                                                            \
      median_impl<T, 16>(C, N, W, H, means2d, conics, depths, opac, rect, tile_off, isect, goff,   \
                         cmask, median, alpha, contrib, nthreads);                                  \
    else                                                                                            \
      return -2;                                                                                    \
    return 0;                                                                                       \
  }                                                                                                 \
  SGPOR_API int sgpor_raster_bwd_##SUF(                                                             \
      int C, int N, int CH, int W, int H, int tile, const void* packed, const int64_t* tile_off,    \
      const Isect* isect, const int64_t* goff, const T* tfinal,                                     \
      const int32_t* last, const T* g_out, const T* g_alpha, T* g_means2d, T* g_conics,            \
      T* g_feats, T* g_opac, const uint8_t* train, int nthreads) {                                 \
    if (tile == 8)                                                                                  \
      return bwd_ch<T, 8>(CH, C, N, W, H, packed, tile_off, isect, goff, tfinal, last, g_out,    \
                          g_alpha, g_means2d, g_conics, g_feats, g_opac, train, nthreads);          \
    if (tile == 16)                                                                                 \
      return bwd_ch<T, 16>(CH, C, N, W, H, packed, tile_off, isect, goff, tfinal, last, g_out,   \
                           g_alpha, g_means2d, g_conics, g_feats, g_opac, train, nthreads);         \
    return -2;                                                                                      \
  }                                                                                                 \
  SGPOR_API double sgpor_ssim_fwd_##SUF(int C, int H, int W, const T* x, const T* y,               \
                                        const T* wmap, T* mom, int nthreads) {                     \
    return ssim::forward<T>(C, H, W, x, y, wmap, mom, nthreads);                                    \
  }                                                                                                 \
  SGPOR_API void sgpor_ssim_bwd_##SUF(int C, int H, int W, const T* x, const T* y, const T* mom,   \
                                      const T* wmap, double scale, T* dx, int nthreads) {          \
    ssim::backward<T>(C, H, W, x, y, mom, wmap, scale, dx, nthreads);                               \
  }                                                                                                 \
  SGPOR_API int64_t sgpor_packed_bytes_##SUF(int CH) {                                              \
    switch (CH) {                                                                                   \
      case 1: return sizeof(GaussPix<T, 1>);                                                        \
      case 2: return sizeof(GaussPix<T, 2>);                                                        \
      case 3: return sizeof(GaussPix<T, 3>);                                                        \
      case 4: return sizeof(GaussPix<T, 4>);                                                        \
      default: return -1;                                                                           \
    }                                                                                               \
  }

SGPOR_DEFINE(float, f32)
SGPOR_API void sgpor_masked_ssd_f32(int T, int KC, int win, int r, int step, const float* cur, int64_t cur_stride,
                                    const float* mask, int64_t mask_stride, const int32_t* tpos,
                                    const float* const* views, const int64_t* vstride,
                                    const int32_t* cand, float* out, int nthreads) {
  match::masked_ssd(T, KC, win, r, step, cur, cur_stride, mask, mask_stride, tpos, match::FloatViews{views, vstride},
                    cand, out, nthreads);
}
SGPOR_API void sgpor_masked_ssd_u8(int T, int KC, int win, int r, int step, const float* cur, int64_t cur_stride,
                                   const float* mask, int64_t mask_stride, const int32_t* tpos,
                                   const uint8_t* const* views, const uint8_t* const* valid,
                                   const int32_t* height, const int32_t* width, int pad, const float* lut,
                                   float sentinel, const int32_t* cand, float* out, int nthreads) {
  match::masked_ssd(T, KC, win, r, step, cur, cur_stride, mask, mask_stride, tpos,
                    match::ByteViews{views, valid, height, width, pad, lut, sentinel}, cand, out, nthreads);
}
SGPOR_DEFINE(double, f64)
