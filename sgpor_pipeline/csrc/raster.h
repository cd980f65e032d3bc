// Tile-based Gaussian rasterizer for the CPU: templates shared by raster.cpp.
//
// Semantics: DESIGN.md section 6 and sgpor_pipeline/gaussians/_raster_common.py (the constants
// below repeat those in Python; tests check both agree). No torch, no Python: plain C++17 +
// OpenMP, called through ctypes with raw pointers to contiguous arrays.
//
// Pipeline per camera: project (cull, EWA covariance, conic, footprint rectangle, tile count),
// bin (stable radix sort of the visible Gaussians by depth, then a counting sort into tiles, so
// every tile list is front to back with ties broken by index), rasterize (OpenMP over tiles; a
// tile's pixels are SIMD lanes: one row of the tile at a time), and the hand-written backward:
// each tile writes one gradient record per intersection into a buffer indexed by the
// intersection's generation id (Gaussian-major), then a per-Gaussian serial sum over its own
// records in a fixed order. No atomics: the result does not depend on the thread count.
#pragma once

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <type_traits>
#include <vector>

#include "fmadd.h"

#ifdef _OPENMP
#include <omp.h>
#endif

namespace sgpor {

constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kAlphaMax = 0.99;
constexpr double kTMin = 1e-4;
constexpr double kMaxSigma = 0.5 * 3.33 * 3.33;
constexpr double kFrustumMargin = 0.3;
constexpr double kQuatEps = 1e-12;
constexpr double kDirEps = 1e-12;

constexpr double kShC0 = 0.28209479177387814;
constexpr double kShC1 = 0.4886025119029199;
constexpr double kShC2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                             -1.0925484305920792, 0.5462742152960396};
constexpr double kShC3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                             0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                             -0.5900435899266435};

// Optional phase timings on stderr (env SGPOR_KERNEL_PROFILE=1), for the benchmark's breakdown.
inline bool profiling() {
  static const bool on = [] {
    const char* e = std::getenv("SGPOR_KERNEL_PROFILE");
    return e && e[0] && e[0] != '0';
  }();
  return on;
}
struct PhaseTimer {
  const char* name;
  std::chrono::steady_clock::time_point t0;
  explicit PhaseTimer(const char* n) : name(n), t0(std::chrono::steady_clock::now()) {}
  ~PhaseTimer() {
    if (profiling()) {
      const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
      std::fprintf(stderr, "[sgpor] %-12s %8.3f ms\n", name, ms);
    }
  }
};

// Work counters of the last forward (0) and backward (1) rasterization: intersections and
// (pixel, Gaussian) SIMD lanes evaluated. Read by the benchmark through sgpor_last_stats().
inline int64_t* stats_slots() {
  static int64_t slots[4] = {0, 0, 0, 0};
  return slots;
}
inline void stats_set(int which, int64_t isects, int64_t lanes) {
  stats_slots()[2 * which] = isects;
  stats_slots()[2 * which + 1] = lanes;
}

// Threads for a phase whose serial run time is about `est_us` microseconds. Every parallel region
// costs a fork and a join; on a busy machine (more runnable threads than cores) each can wait for
// a descheduled thread for a whole scheduler time slice, so phases worth less than ~1.5 ms run
// serially. Only thread counts change with this, never results.
inline int par_threads(int nthreads, double est_us) { return est_us > 1500.0 ? nthreads : 1; }

// ---------------------------------------------------------------------------------------------
// 2^x for the compositing loops (the loops work with sigma * log2(e), so exp(-sigma) is
// 2^(-sigma log2 e)). The float version is a branch-free Cephes-style polynomial (a few 1e-8
// relative error) that gcc vectorises; the double version is std::exp2 (the double kernel exists
// for gradient checks, not for speed).
inline float exp2_kernel(float x) {
  x = x < -126.0f ? -126.0f : x;
  x = x > 126.0f ? 126.0f : x;
  const float n = std::floor(x + 0.5f);
  const float r = x - n;  // [-0.5, 0.5]
  float p = 1.535336188319500e-4f;
  p = fmadd(p, r, 1.339887440266574e-3f);
  p = fmadd(p, r, 9.618437357674640e-3f);
  p = fmadd(p, r, 5.550332471162809e-2f);
  p = fmadd(p, r, 2.402264791363012e-1f);
  p = fmadd(p, r, 6.931472028550421e-1f);
  p = fmadd(p, r, 1.0f);
  const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof(scale));
  return p * scale;
}
inline double exp2_kernel(double x) { return std::exp2(x); }
constexpr double kLog2e = 1.4426950408889634;
// The compositing loops evaluate exp2(-sigma log2 e) on every lane of a row, also far outside the
// Gaussian (most lanes of a small one). Unclamped, those values and the products made of them
// fall below 2^-126: subnormal floats, which x86 cores handle in microcode at ~100 cycles an
// operation (measured: this clamp made the forward 43 % and the backward 34 % faster on the demo
// fit's model, 1 thread). Bitwise the same results: a lane with sigma log2 e > 64 has alpha
// < 2^-64 < kAlphaMin, so it was already out in both directions.
constexpr double kSigmaLog2Max = 64.0;

template <typename T>
inline T clampv(T x, T lo, T hi) {
  return x < lo ? lo : (x > hi ? hi : x);
}

// log(x) for the footprint threshold: a branch-free Cephes-style polynomial (about 1 ulp for
// positive normal x) so that the projection loop vectorises; std::log for double.
inline float log_kernel(float x) {
  int32_t bits;
  std::memcpy(&bits, &x, sizeof(bits));
  const int32_t e = ((bits >> 23) & 0xff) - 126;  // x = m 2^e, m in [0.5, 1)
  bits = (bits & 0x007fffff) | 0x3f000000;
  float m;
  std::memcpy(&m, &bits, sizeof(m));
  const bool lt = m < 0.707106781186547524f;
  const float ef = float(e) - (lt ? 1.0f : 0.0f);
  m = lt ? m + m - 1.0f : m - 1.0f;
  const float z = m * m;
  float y = 7.0376836292e-2f;
  y = fmadd(y, m, -1.1514610310e-1f);
  y = fmadd(y, m, 1.1676998740e-1f);
  y = fmadd(y, m, -1.2420140846e-1f);
  y = fmadd(y, m, 1.4249322787e-1f);
  y = fmadd(y, m, -1.6668057665e-1f);
  y = fmadd(y, m, 2.0000714765e-1f);
  y = fmadd(y, m, -2.4999993993e-1f);
  y = fmadd(y, m, 3.3333331174e-1f);
  y = y * m * z;
  y = fmadd(ef, -2.12194440e-4f, y);
  y = fmadd(-0.5f, z, y);
  return fmadd(ef, 0.693359375f, m + y);
}
inline double log_kernel(double x) { return std::log(x); }

template <typename T>
inline T footprint_thr(T o) {  // largest sigma inside the footprint (needs o >= 1/255)
  return std::min(T(kMaxSigma), log_kernel(T(255) * o));
}

// ---------------------------------------------------------------------------------------------
// Projection. The per-Gaussian math is written branch-free (selects, no early exits) so that the
// loops over Gaussians vectorise; culled Gaussians compute with safe stand-in values and are
// masked. Covariance: with M = Rq diag(s) and V = R M (camera frame), the 2D covariance is
// (J V)(J V)^T + eps2d I, J the EWA Jacobian.
template <typename T>
struct Camera {
  T R[9], t[3];
  T fx, fy, cx, cy;
  T lim_xp, lim_xn, lim_yp, lim_yn;

  Camera(const T* viewmat, const T* K, int W, int H) {
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) R[i * 3 + j] = viewmat[i * 4 + j];
      t[i] = viewmat[i * 4 + 3];
    }
    fx = K[0];
    fy = K[4];
    cx = K[2];
    cy = K[5];
    const T tan_x = T(0.5) * T(W) / fx;
    const T tan_y = T(0.5) * T(H) / fy;
    lim_xp = (T(W) - cx) / fx + T(kFrustumMargin) * tan_x;
    lim_xn = cx / fx + T(kFrustumMargin) * tan_x;
    lim_yp = (T(H) - cy) / fy + T(kFrustumMargin) * tan_y;
    lim_yn = cy / fy + T(kFrustumMargin) * tan_y;
  }
};

template <typename T>
struct Proj {
  T x, y, z, zs;     // camera coordinates; zs = z, or 1 when culled by depth
  bool zok;          // near <= z <= far
  T rx, ry;          // x/z, y/z clamped to the widened frustum
  bool inx, iny;     // whether x/z, y/z were inside (not clamped)
  T q[4], qn;        // normalised quaternion and |q|
  T Rq[9];           // rotation of the Gaussian
  T V[9];            // R Rq diag(s)
  T T0[3], T1[3];    // rows of J V
  T A, B, Cc;        // 2D covariance + eps2d
};

template <typename T>
inline void project_core(const Camera<T>& k, const T* m, const T* qin, const T* s, T near, T far,
                         T eps2d, Proj<T>& P) {
  const T* R = k.R;
  P.x = R[0] * m[0] + R[1] * m[1] + R[2] * m[2] + k.t[0];
  P.y = R[3] * m[0] + R[4] * m[1] + R[5] * m[2] + k.t[1];
  P.z = R[6] * m[0] + R[7] * m[1] + R[8] * m[2] + k.t[2];
  P.zok = (P.z >= near) & (P.z <= far);
  P.zs = P.zok ? P.z : T(1);
  P.qn = std::sqrt(qin[0] * qin[0] + qin[1] * qin[1] + qin[2] * qin[2] + qin[3] * qin[3]);
  const T inv = T(1) / std::max(P.qn, T(kQuatEps));
  for (int i = 0; i < 4; ++i) P.q[i] = qin[i] * inv;
  const T w = P.q[0], x = P.q[1], y = P.q[2], z = P.q[3];
  P.Rq[0] = 1 - 2 * (y * y + z * z);
  P.Rq[1] = 2 * (x * y - w * z);
  P.Rq[2] = 2 * (x * z + w * y);
  P.Rq[3] = 2 * (x * y + w * z);
  P.Rq[4] = 1 - 2 * (x * x + z * z);
  P.Rq[5] = 2 * (y * z - w * x);
  P.Rq[6] = 2 * (x * z - w * y);
  P.Rq[7] = 2 * (y * z + w * x);
  P.Rq[8] = 1 - 2 * (x * x + y * y);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j)
      P.V[i * 3 + j] = (R[i * 3] * P.Rq[j] + R[i * 3 + 1] * P.Rq[3 + j] + R[i * 3 + 2] * P.Rq[6 + j]) * s[j];
  const T xz = P.x / P.zs, yz = P.y / P.zs;
  P.inx = (xz >= -k.lim_xn) & (xz <= k.lim_xp);
  P.iny = (yz >= -k.lim_yn) & (yz <= k.lim_yp);
  P.rx = clampv(xz, -k.lim_xn, k.lim_xp);
  P.ry = clampv(yz, -k.lim_yn, k.lim_yp);
  const T iz = T(1) / P.zs;
  const T j00 = k.fx * iz, j02 = -k.fx * P.rx * iz, j11 = k.fy * iz, j12 = -k.fy * P.ry * iz;
  for (int j = 0; j < 3; ++j) {
    P.T0[j] = j00 * P.V[j] + j02 * P.V[6 + j];
    P.T1[j] = j11 * P.V[3 + j] + j12 * P.V[6 + j];
  }
  P.A = P.T0[0] * P.T0[0] + P.T0[1] * P.T0[1] + P.T0[2] * P.T0[2] + eps2d;
  P.B = P.T0[0] * P.T1[0] + P.T0[1] * P.T1[1] + P.T0[2] * P.T1[2];
  P.Cc = P.T1[0] * P.T1[0] + P.T1[1] * P.T1[1] + P.T1[2] * P.T1[2] + eps2d;
}

// Projection forward: per (camera, Gaussian). Returns the total number of tile intersections.
template <typename T>
int64_t project_fwd(int C, int N, const T* means, const T* quats, const T* scales, const T* opac,
                    const T* viewmats, const T* Ks, int W, int H, T near, T far, T eps2d, int tile,
                    T* means2d, T* conics, T* depths, int32_t* radii, int32_t* rect,
                    int32_t* ntiles, int nthreads) {
  PhaseTimer timer_("project_fwd");
  int shift = 0;
  while ((1 << shift) < tile) ++shift;
  const T big = T(std::max(W, H) + 2);
  int64_t total = 0;
  for (int c = 0; c < C; ++c) {
    const Camera<T> cam(viewmats + 16 * c, Ks + 9 * c, W, H);
    int64_t sum = 0;
#pragma omp parallel for simd num_threads(par_threads(nthreads, 0.008 * N)) schedule(static) reduction(+ : sum)
    for (int64_t n = 0; n < N; ++n) {
      const int64_t cn = int64_t(c) * N + n;
      Proj<T> P;
      project_core(cam, means + 3 * n, quats + 4 * n, scales + 3 * n, near, far, eps2d, P);
      const T o = opac[n];
      const T det = P.A * P.Cc - P.B * P.B;
      bool vis = P.zok & (det > T(0)) & (o >= T(kAlphaMin));
      const T idet = T(1) / (vis ? det : T(1));
      const T u = cam.fx * P.x / P.zs + cam.cx;
      const T v = cam.fy * P.y / P.zs + cam.cy;
      const T thr = footprint_thr(std::max(o, T(kAlphaMin)));
      const T hx = std::sqrt(T(2) * thr * (vis ? P.A : T(1)));
      const T hy = std::sqrt(T(2) * thr * (vis ? P.Cc : T(1)));
      const T x0 = std::max(clampv(std::ceil(u - hx - T(0.5)), T(-1), big), T(0));
      const T x1 = std::min(clampv(std::floor(u + hx - T(0.5)), T(-1), big), T(W - 1));
      const T y0 = std::max(clampv(std::ceil(v - hy - T(0.5)), T(-1), big), T(0));
      const T y1 = std::min(clampv(std::floor(v + hy - T(0.5)), T(-1), big), T(H - 1));
      vis = vis & (x0 <= x1) & (y0 <= y1);
      depths[cn] = P.z;
      means2d[2 * cn] = vis ? u : T(0);
      means2d[2 * cn + 1] = vis ? v : T(0);
      conics[3 * cn] = vis ? P.Cc * idet : T(0);
      conics[3 * cn + 1] = vis ? -P.B * idet : T(0);
      conics[3 * cn + 2] = vis ? P.A * idet : T(0);
      radii[cn] = vis ? int32_t(std::ceil(std::max(hx, hy))) : 0;
      const int32_t ix0 = vis ? int32_t(x0) : 0, ix1 = vis ? int32_t(x1) : -1;
      const int32_t iy0 = vis ? int32_t(y0) : 0, iy1 = vis ? int32_t(y1) : -1;
      rect[4 * cn] = ix0;
      rect[4 * cn + 1] = ix1;
      rect[4 * cn + 2] = iy0;
      rect[4 * cn + 3] = iy1;
      const int32_t nt = vis ? ((ix1 >> shift) - (ix0 >> shift) + 1) * ((iy1 >> shift) - (iy0 >> shift) + 1) : 0;
      ntiles[cn] = nt;
      sum += nt;
    }
    total += sum;
  }
  return total;
}

// Projection backward: gradients of means2d, conics, depths -> means, quats, scales, summed over
// cameras in camera order (parallel over Gaussians: deterministic).
template <typename T>
void project_bwd(int C, int N, const T* means, const T* quats, const T* scales, const T* viewmats,
                 const T* Ks, int W, int H, T near, T far, T eps2d, const int32_t* radii,
                 const T* g_means2d, const T* g_conics, const T* g_depths, T* g_means, T* g_quats,
                 T* g_scales, int nthreads) {
  PhaseTimer timer_("project_bwd");
  std::vector<Camera<T>> cams;
  cams.reserve(C);
  for (int c = 0; c < C; ++c) cams.emplace_back(viewmats + 16 * c, Ks + 9 * c, W, H);
  const Camera<T>* camp = cams.data();
  // Only the Gaussians with a gradient from some camera (most are hidden behind others or off
  // screen); the others' gradients are exactly zero.
  std::vector<int32_t> active;
  active.reserve(N);
  for (int64_t n = 0; n < N; ++n) {
    bool any = false;
    for (int c = 0; c < C && !any; ++c) {
      const int64_t cn = int64_t(c) * N + n;
      any = (g_depths && g_depths[cn] != T(0)) ||
            (radii[cn] > 0 && (g_means2d[2 * cn] != T(0) || g_means2d[2 * cn + 1] != T(0) ||
                               g_conics[3 * cn] != T(0) || g_conics[3 * cn + 1] != T(0) ||
                               g_conics[3 * cn + 2] != T(0)));
    }
    if (any) {
      active.push_back(int32_t(n));
    } else {
      for (int j = 0; j < 3; ++j) g_means[3 * n + j] = T(0), g_scales[3 * n + j] = T(0);
      for (int j = 0; j < 4; ++j) g_quats[4 * n + j] = T(0);
    }
  }
  const int64_t A = int64_t(active.size());
  const int32_t* act = active.data();
#pragma omp parallel for simd num_threads(par_threads(nthreads, 0.07 * double(A) * C)) schedule(static)
  for (int64_t i = 0; i < A; ++i) {
    const int64_t n = act[i];
    T gm[3] = {0, 0, 0}, gq[4] = {0, 0, 0, 0}, gs[3] = {0, 0, 0};
    for (int c = 0; c < C; ++c) {
      const int64_t cn = int64_t(c) * N + n;
      const Camera<T>& k = camp[c];
      Proj<T> P;
      project_core(k, means + 3 * n, quats + 4 * n, scales + 3 * n, near, far, eps2d, P);
      const bool vis = radii[cn] > 0;
      const T gu = vis ? g_means2d[2 * cn] : T(0), gv = vis ? g_means2d[2 * cn + 1] : T(0);
      const T ga = vis ? g_conics[3 * cn] : T(0), gb = vis ? g_conics[3 * cn + 1] : T(0);
      const T gc = vis ? g_conics[3 * cn + 2] : T(0);
      const T gz = g_depths ? g_depths[cn] : T(0);
      // conic = inverse(cov2): dCov = -Q G Q, Q = [[a,b],[b,c]], G = [[ga, gb/2],[gb/2, gc]]
      const T det = P.A * P.Cc - P.B * P.B;
      const T idet = T(1) / (vis ? det : T(1));
      const T a = P.Cc * idet, b = -P.B * idet, c2 = P.A * idet;
      const T G01 = T(0.5) * gb;
      const T QG00 = a * ga + b * G01, QG01 = a * G01 + b * gc;
      const T QG10 = b * ga + c2 * G01, QG11 = b * G01 + c2 * gc;
      const T dA = -(QG00 * a + QG01 * b);
      const T dB = -(QG00 * b + QG01 * c2);  // per off-diagonal entry of the symmetric matrix
      const T dC = -(QG10 * b + QG11 * c2);
      // cov2 = T T^T: dT = 2 Gc T
      T dT0[3], dT1[3];
      for (int j = 0; j < 3; ++j) {
        dT0[j] = T(2) * (dA * P.T0[j] + dB * P.T1[j]);
        dT1[j] = T(2) * (dB * P.T0[j] + dC * P.T1[j]);
      }
      const T iz = T(1) / P.zs;
      const T j00 = k.fx * iz, j02 = -k.fx * P.rx * iz, j11 = k.fy * iz, j12 = -k.fy * P.ry * iz;
      // T0 = j00 V0 + j02 V2, T1 = j11 V1 + j12 V2
      T dV[9];
      for (int j = 0; j < 3; ++j) {
        dV[j] = j00 * dT0[j];
        dV[3 + j] = j11 * dT1[j];
        dV[6 + j] = j02 * dT0[j] + j12 * dT1[j];
      }
      const T dj00 = dT0[0] * P.V[0] + dT0[1] * P.V[1] + dT0[2] * P.V[2];
      const T dj02 = dT0[0] * P.V[6] + dT0[1] * P.V[7] + dT0[2] * P.V[8];
      const T dj11 = dT1[0] * P.V[3] + dT1[1] * P.V[4] + dT1[2] * P.V[5];
      const T dj12 = dT1[0] * P.V[6] + dT1[1] * P.V[7] + dT1[2] * P.V[8];
      // J -> camera coordinates (x, y, z)
      const T iz2 = iz * iz;
      T gpx = k.fx * iz * gu, gpy = k.fy * iz * gv;
      T gpz = gz - k.fx * P.x * iz2 * gu - k.fy * P.y * iz2 * gv;
      gpz += -k.fx * iz2 * dj00 + k.fx * P.rx * iz2 * dj02 - k.fy * iz2 * dj11 + k.fy * P.ry * iz2 * dj12;
      const T grx = P.inx ? -k.fx * iz * dj02 : T(0), gry = P.iny ? -k.fy * iz * dj12 : T(0);
      gpx += grx * iz;
      gpy += gry * iz;
      gpz += -(grx * P.x + gry * P.y) * iz2;
      gpx = P.zok ? gpx : T(0);
      gpy = P.zok ? gpy : T(0);
      gpz = P.zok ? gpz : gz;
      // V = R Rq diag(s): dRq = R^T dV diag(s), ds_j = sum_i (R^T dV)_ij Rq_ij
      const T* R = k.R;
      T dR[9];
      for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
          const T dM = R[i] * dV[j] + R[3 + i] * dV[3 + j] + R[6 + i] * dV[6 + j];
          dR[i * 3 + j] = dM * scales[3 * n + j];
          gs[j] += dM * P.Rq[i * 3 + j];
        }
      const T w = P.q[0], qx = P.q[1], qy = P.q[2], qz = P.q[3];
      T dq[4];
      dq[0] = 2 * (-qz * dR[1] + qy * dR[2] + qz * dR[3] - qx * dR[5] - qy * dR[6] + qx * dR[7]);
      dq[1] = 2 * (qy * dR[1] + qz * dR[2] + qy * dR[3] - 2 * qx * dR[4] - w * dR[5] + qz * dR[6] + w * dR[7] - 2 * qx * dR[8]);
      dq[2] = 2 * (-2 * qy * dR[0] + qx * dR[1] + w * dR[2] + qx * dR[3] + qz * dR[5] - w * dR[6] + qz * dR[7] - 2 * qy * dR[8]);
      dq[3] = 2 * (-2 * qz * dR[0] - w * dR[1] + qx * dR[2] + w * dR[3] - 2 * qz * dR[4] + qy * dR[5] + qx * dR[6] + qy * dR[7]);
      const bool qbig = P.qn >= T(kQuatEps);
      const T dot = qbig ? P.q[0] * dq[0] + P.q[1] * dq[1] + P.q[2] * dq[2] + P.q[3] * dq[3] : T(0);
      const T qden = qbig ? P.qn : T(kQuatEps);
      for (int i = 0; i < 4; ++i) gq[i] += (dq[i] - P.q[i] * dot) / qden;
      // p = R m + t
      for (int j = 0; j < 3; ++j) gm[j] += R[j] * gpx + R[3 + j] * gpy + R[6 + j] * gpz;
    }
    for (int j = 0; j < 3; ++j) g_means[3 * n + j] = gm[j];
    for (int j = 0; j < 4; ++j) g_quats[4 * n + j] = gq[j];
    for (int j = 0; j < 3; ++j) g_scales[3 * n + j] = gs[j];
  }
}

// ---------------------------------------------------------------------------------------------
// Spherical harmonics (3DGS constants): rgb [C,N,3] = max(SH(dir) + 0.5, 0), dir = mean - campos.
template <int DEG, typename T>
inline void sh_basis(T x, T y, T z, T* b) {
  b[0] = T(kShC0);
  if (DEG < 1) return;
  b[1] = -T(kShC1) * y;
  b[2] = T(kShC1) * z;
  b[3] = -T(kShC1) * x;
  if (DEG < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  b[4] = T(kShC2[0]) * xy;
  b[5] = T(kShC2[1]) * yz;
  b[6] = T(kShC2[2]) * (2 * zz - xx - yy);
  b[7] = T(kShC2[3]) * xz;
  b[8] = T(kShC2[4]) * (xx - yy);
  if (DEG < 3) return;
  b[9] = T(kShC3[0]) * y * (3 * xx - yy);
  b[10] = T(kShC3[1]) * xy * z;
  b[11] = T(kShC3[2]) * y * (4 * zz - xx - yy);
  b[12] = T(kShC3[3]) * z * (2 * zz - 3 * xx - 3 * yy);
  b[13] = T(kShC3[4]) * x * (4 * zz - xx - yy);
  b[14] = T(kShC3[5]) * z * (xx - yy);
  b[15] = T(kShC3[6]) * x * (xx - 3 * yy);
}

// gdir += sum_k v[k] * d basis_k / d(x, y, z)
template <int DEG, typename T>
inline void sh_basis_vjp(T x, T y, T z, const T* v, T* gdir) {
  if (DEG < 1) return;
  const T c1 = T(kShC1);
  gdir[0] += -c1 * v[3];
  gdir[1] += -c1 * v[1];
  gdir[2] += c1 * v[2];
  if (DEG < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  gdir[0] += T(kShC2[0]) * y * v[4] - T(kShC2[2]) * 2 * x * v[6] + T(kShC2[3]) * z * v[7] + T(kShC2[4]) * 2 * x * v[8];
  gdir[1] += T(kShC2[0]) * x * v[4] + T(kShC2[1]) * z * v[5] - T(kShC2[2]) * 2 * y * v[6] - T(kShC2[4]) * 2 * y * v[8];
  gdir[2] += T(kShC2[1]) * y * v[5] + T(kShC2[2]) * 4 * z * v[6] + T(kShC2[3]) * x * v[7];
  if (DEG < 3) return;
  gdir[0] += T(kShC3[0]) * 6 * xy * v[9] + T(kShC3[1]) * yz * v[10] - T(kShC3[2]) * 2 * xy * v[11]
           - T(kShC3[3]) * 6 * xz * v[12] + T(kShC3[4]) * (4 * zz - 3 * xx - yy) * v[13]
           + T(kShC3[5]) * 2 * xz * v[14] + T(kShC3[6]) * (3 * xx - 3 * yy) * v[15];
  gdir[1] += T(kShC3[0]) * (3 * xx - 3 * yy) * v[9] + T(kShC3[1]) * xz * v[10]
           + T(kShC3[2]) * (4 * zz - xx - 3 * yy) * v[11] - T(kShC3[3]) * 6 * yz * v[12]
           - T(kShC3[4]) * 2 * xy * v[13] - T(kShC3[5]) * 2 * yz * v[14] - T(kShC3[6]) * 6 * xy * v[15];
  gdir[2] += T(kShC3[1]) * xy * v[10] + T(kShC3[2]) * 8 * yz * v[11]
           + T(kShC3[3]) * (6 * zz - 3 * xx - 3 * yy) * v[12] + T(kShC3[4]) * 8 * xz * v[13]
           + T(kShC3[5]) * (xx - yy) * v[14];
}

template <typename T>
inline void campos_of(const T* viewmat, T* cp) {  // -R^T t
  for (int j = 0; j < 3; ++j)
    cp[j] = -(viewmat[j] * viewmat[3] + viewmat[4 + j] * viewmat[7] + viewmat[8 + j] * viewmat[11]);
}

// The SH coefficients (or their gradients: P = T*) of Gaussian n come in two row arrays: the DC
// term at sh0 + n * stride0 and the KN others at shN + n * strideN (3 values each, channel fastest).
// One [N,K,3] tensor is sh0 = sh, shN = sh + 3, both strides 3K; the model's two parameters are
// passed without a copy.
template <typename P>
struct ShRowsOf {
  P sh0;
  int64_t stride0;
  P shN;
  int64_t strideN;
  int KN;
  P coef(int64_t n, int k) const {  // (k is a constant in the unrolled loops: no branch)
    return k == 0 ? sh0 + n * stride0 : shN + n * strideN + 3 * (k - 1);
  }
};
template <typename T>
using ShRows = ShRowsOf<const T*>;

template <int DEG, typename T>
void sh_fwd_deg(int C, int N, const T* means, const ShRows<T>& sh, const T* viewmats, T* rgb,
                int nthreads) {
  constexpr int NB = (DEG + 1) * (DEG + 1);
  for (int c = 0; c < C; ++c) {
    T cp[3];
    campos_of(viewmats + 16 * c, cp);
    const T cx = cp[0], cy = cp[1], cz = cp[2];
#pragma omp parallel for simd num_threads(par_threads(nthreads, 0.03 * N)) schedule(static)
    for (int64_t n = 0; n < N; ++n) {
      const T dx = means[3 * n] - cx, dy = means[3 * n + 1] - cy, dz = means[3 * n + 2] - cz;
      const T idn = T(1) / std::max(std::sqrt(dx * dx + dy * dy + dz * dz), T(kDirEps));
      T b[16];
      sh_basis<DEG>(dx * idn, dy * idn, dz * idn, b);
      for (int ch = 0; ch < 3; ++ch) {
        T acc = 0;
        for (int k = 0; k < NB; ++k) acc += b[k] * sh.coef(n, k)[ch];
        rgb[(int64_t(c) * N + n) * 3 + ch] = std::max(acc + T(0.5), T(0));
      }
    }
  }
}

// g_means is accumulated into (+=), the coefficient gradients g_sh (rows as sh's) overwritten
// (coefficients above the degree get 0). Cameras are summed in camera order (outer loop),
// Gaussians in parallel: deterministic.
template <int DEG, typename T>
void sh_bwd_deg(int C, int N, const T* means, const ShRows<T>& sh, const T* viewmats, const T* g_rgb,
                T* g_means, const ShRowsOf<T*>& g_sh, int nthreads) {
  constexpr int NB = (DEG + 1) * (DEG + 1);
  const int KN = g_sh.KN;
  if (KN + 1 > NB) {
#pragma omp parallel for num_threads(par_threads(nthreads, 0.002 * double(N) * (KN + 1))) schedule(static)
    for (int64_t n = 0; n < N; ++n)
      for (int i = (NB - 1) * 3; i < KN * 3; ++i) g_sh.shN[n * g_sh.strideN + i] = 0;
  }
  for (int c = 0; c < C; ++c) {
    T cp[3];
    campos_of(viewmats + 16 * c, cp);
    const T cx = cp[0], cy = cp[1], cz = cp[2];
    const bool first = c == 0;
    const T* gr = g_rgb + int64_t(c) * N * 3;
#pragma omp parallel for num_threads(par_threads(nthreads, 0.05 * N)) schedule(static)
    for (int64_t n = 0; n < N; ++n) {
      // Most Gaussians get no colour gradient from a view (hidden behind others or off screen: 58 %
      // on the demo fit's views); theirs is exactly zero, so they are skipped.
      if (gr[3 * n] == T(0) && gr[3 * n + 1] == T(0) && gr[3 * n + 2] == T(0)) {
        if (first)
          for (int k = 0; k < NB; ++k)
            for (int ch = 0; ch < 3; ++ch) g_sh.coef(n, k)[ch] = T(0);
        continue;
      }
      const T dx = means[3 * n] - cx, dy = means[3 * n + 1] - cy, dz = means[3 * n + 2] - cz;
      const T rn = std::sqrt(dx * dx + dy * dy + dz * dz);
      const T idn = T(1) / std::max(rn, T(kDirEps));
      const T x = dx * idn, y = dy * idn, z = dz * idn;
      T b[16];
      sh_basis<DEG>(x, y, z, b);
      T g[3];
      for (int ch = 0; ch < 3; ++ch) {
        T acc = 0;
        for (int k = 0; k < NB; ++k) acc += b[k] * sh.coef(n, k)[ch];
        g[ch] = (acc + T(0.5) >= T(0)) ? gr[3 * n + ch] : T(0);
      }
      for (int k = 0; k < NB; ++k) {
        T* gs = g_sh.coef(n, k);
        for (int ch = 0; ch < 3; ++ch) gs[ch] = (first ? T(0) : gs[ch]) + b[k] * g[ch];
      }
      T v[16];
      for (int k = 0; k < NB; ++k) {
        const T* s = sh.coef(n, k);
        v[k] = s[0] * g[0] + s[1] * g[1] + s[2] * g[2];
      }
      T gdir[3] = {0, 0, 0};
      sh_basis_vjp<DEG>(x, y, z, v, gdir);
      // dir = d / max(|d|, eps): the projection only when |d| >= eps (clamp_min passes no gradient)
      const T dot = rn >= T(kDirEps) ? gdir[0] * x + gdir[1] * y + gdir[2] * z : T(0);
      g_means[3 * n] += (gdir[0] - dot * x) * idn;
      g_means[3 * n + 1] += (gdir[1] - dot * y) * idn;
      g_means[3 * n + 2] += (gdir[2] - dot * z) * idn;
    }
  }
}

template <typename T>
void sh_fwd(int C, int N, int deg, const T* means, const ShRows<T>& sh, const T* viewmats, T* rgb,
            int nthreads) {
  PhaseTimer timer_("sh_fwd");
  switch (deg) {
    case 0: sh_fwd_deg<0>(C, N, means, sh, viewmats, rgb, nthreads); break;
    case 1: sh_fwd_deg<1>(C, N, means, sh, viewmats, rgb, nthreads); break;
    case 2: sh_fwd_deg<2>(C, N, means, sh, viewmats, rgb, nthreads); break;
    default: sh_fwd_deg<3>(C, N, means, sh, viewmats, rgb, nthreads); break;
  }
}

template <typename T>
void sh_bwd(int C, int N, int deg, const T* means, const ShRows<T>& sh, const T* viewmats,
            const T* g_rgb, T* g_means, const ShRowsOf<T*>& g_sh, int nthreads) {
  PhaseTimer timer_("sh_bwd");
  switch (deg) {
    case 0: sh_bwd_deg<0>(C, N, means, sh, viewmats, g_rgb, g_means, g_sh, nthreads); break;
    case 1: sh_bwd_deg<1>(C, N, means, sh, viewmats, g_rgb, g_means, g_sh, nthreads); break;
    case 2: sh_bwd_deg<2>(C, N, means, sh, viewmats, g_rgb, g_means, g_sh, nthreads); break;
    default: sh_bwd_deg<3>(C, N, means, sh, viewmats, g_rgb, g_means, g_sh, nthreads); break;
  }
}

// ---------------------------------------------------------------------------------------------
// Binning: tile_off [C*TT+1], isect [M] sorted by (camera, tile, depth, index), gauss_off [C*N+1].
// An intersection holds the Gaussian (index within its camera) and its generation id
// gauss_off[c*N+n] + k for the k-th tile of Gaussian n in row-major tile order: the index of its
// per-intersection records, so that each Gaussian's records are contiguous.
struct Isect {
  int32_t gid, gen;
};

// Stable LSD radix sort of (key, value) pairs, 11 bits per pass; passes where every key has the
// same digit are skipped.
template <typename K>
inline void radix_sort_pairs(std::vector<K>& keys, std::vector<int32_t>& vals) {
  const size_t n = keys.size();
  std::vector<K> k2(n);
  std::vector<int32_t> v2(n);
  constexpr int kBits = 11, kBuckets = 1 << kBits;
  constexpr int kPasses = (int(sizeof(K)) * 8 + kBits - 1) / kBits;
  std::vector<size_t> cnt(kBuckets + 1);
  for (int pass = 0; pass < kPasses; ++pass) {
    const int shift = pass * kBits;
    std::fill(cnt.begin(), cnt.end(), 0);
    for (size_t i = 0; i < n; ++i) cnt[((keys[i] >> shift) & (kBuckets - 1)) + 1]++;
    bool trivial = false;
    for (int b = 1; b <= kBuckets; ++b) trivial = trivial || cnt[b] == n;
    if (trivial) continue;
    for (int b = 0; b < kBuckets; ++b) cnt[b + 1] += cnt[b];
    for (size_t i = 0; i < n; ++i) {
      const size_t pos = cnt[(keys[i] >> shift) & (kBuckets - 1)]++;
      k2[pos] = keys[i];
      v2[pos] = vals[i];
    }
    keys.swap(k2);
    vals.swap(v2);
  }
}

inline uint32_t depth_key(float z) {
  uint32_t u;
  std::memcpy(&u, &z, 4);
  return (u & 0x80000000u) ? ~u : (u | 0x80000000u);  // order-preserving for any sign
}
inline uint64_t depth_key(double z) {
  uint64_t u;
  std::memcpy(&u, &z, 8);
  return (u & 0x8000000000000000ull) ? ~u : (u | 0x8000000000000000ull);
}

// Tile lists of every camera. The visible Gaussians are sorted by depth (ties: by index), cut into
// one contiguous chunk per thread; each chunk counts and then fills its intersections at offsets
// (tile, chunk)-major, so every tile list is in global depth order whatever the thread count.
template <typename T>
void bin(int C, int N, int W, int H, int tile, const T* depths, const int32_t* rect,
         const int32_t* ntiles, int64_t* tile_off, Isect* isect, int64_t* gauss_off,
         int nthreads) {
  PhaseTimer timer_("bin");
  using Key = decltype(depth_key(T(0)));
  const int tw = (W + tile - 1) / tile, th = (H + tile - 1) / tile;
  const int64_t TT = int64_t(tw) * th;
  int shift = 0;
  while ((1 << shift) < tile) ++shift;
  int64_t run = 0;
  std::vector<int64_t> cam_start(C + 1);
  for (int c = 0; c < C; ++c) {
    cam_start[c] = run;
    for (int64_t n = 0; n < N; ++n) {
      gauss_off[int64_t(c) * N + n] = run;
      run += ntiles[int64_t(c) * N + n];
    }
  }
  cam_start[C] = run;
  gauss_off[int64_t(C) * N] = run;
  const int nchunks = par_threads(nthreads, 0.01 * double(run));
  std::vector<int64_t> counts(size_t(nchunks) * TT);
  for (int c = 0; c < C; ++c) {
    const int64_t base = int64_t(c) * N;
    std::vector<Key> keys;
    std::vector<int32_t> ids;
    keys.reserve(N);
    ids.reserve(N);
    std::fill(counts.begin(), counts.end(), 0);
    for (int64_t n = 0; n < N; ++n) {
      if (ntiles[base + n] > 0) {
        keys.push_back(depth_key(depths[base + n]));
        ids.push_back(int32_t(n));
        if (nchunks == 1) {  // one chunk: count now, in index order (sequential reads)
          const int32_t* r = rect + 4 * (base + n);
          for (int ty = r[2] >> shift; ty <= (r[3] >> shift); ++ty)
            for (int tx = r[0] >> shift; tx <= (r[1] >> shift); ++tx) counts[int64_t(ty) * tw + tx]++;
        }
      }
    }
    radix_sort_pairs(keys, ids);
    const int64_t nv = int64_t(ids.size());
    if (nchunks > 1) {
#pragma omp parallel for num_threads(nchunks) schedule(static, 1)
      for (int ch = 0; ch < nchunks; ++ch) {
        int64_t* cnt = &counts[size_t(ch) * TT];
        for (int64_t i = nv * ch / nchunks; i < nv * (ch + 1) / nchunks; ++i) {
          const int32_t* r = rect + 4 * (base + ids[i]);
          for (int ty = r[2] >> shift; ty <= (r[3] >> shift); ++ty)
            for (int tx = r[0] >> shift; tx <= (r[1] >> shift); ++tx) cnt[int64_t(ty) * tw + tx]++;
        }
      }
    }
    int64_t pos = cam_start[c];
    int64_t* toff = tile_off + int64_t(c) * TT;
    for (int64_t t = 0; t < TT; ++t) {
      toff[t] = pos;
      for (int ch = 0; ch < nchunks; ++ch) {
        const int64_t k = counts[size_t(ch) * TT + t];
        counts[size_t(ch) * TT + t] = pos;  // becomes the chunk's cursor in this tile
        pos += k;
      }
    }
    if (c == C - 1) toff[TT] = pos;
#pragma omp parallel for num_threads(nchunks) schedule(static, 1)
    for (int ch = 0; ch < nchunks; ++ch) {
      int64_t* cur = &counts[size_t(ch) * TT];
      const int64_t i1 = nv * (ch + 1) / nchunks;
      for (int64_t i = nv * ch / nchunks; i < i1; ++i) {
        if (i + 8 < i1) {  // depth order = random order: fetch ahead
          __builtin_prefetch(rect + 4 * (base + ids[i + 8]));
          __builtin_prefetch(gauss_off + base + ids[i + 8]);
        }
        const int32_t n = ids[i];
        const int32_t* r = rect + 4 * (base + n);
        int64_t g = gauss_off[base + n];
        for (int ty = r[2] >> shift; ty <= (r[3] >> shift); ++ty)
          for (int tx = r[0] >> shift; tx <= (r[1] >> shift); ++tx) {
            const int64_t q = cur[int64_t(ty) * tw + tx]++;
            isect[q] = Isect{n, int32_t(g++)};
          }
      }
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Rasterization.
template <typename T, int CH>
struct alignas(16) GaussPix {
  T u, v, a, b, c, o, thr;
  int32_t x0, x1, y0, y1;
  T f[CH];
};

template <typename T, int CH>
void pack_gaussians(int C, int N, const T* means2d, const T* conics, const T* feats, const T* opac,
                    const int32_t* rect, GaussPix<T, CH>* gp, int nthreads) {
  PhaseTimer timer_("pack_gaussians");
  const int64_t CN = int64_t(C) * N;
#pragma omp parallel for num_threads(par_threads(nthreads, 0.012 * double(N) * C)) schedule(static)
  for (int64_t cn = 0; cn < CN; ++cn) {
    const int64_t n = cn % N;
    GaussPix<T, CH>& g = gp[cn];
    g.u = means2d[2 * cn];
    g.v = means2d[2 * cn + 1];
    g.a = conics[3 * cn];
    g.b = conics[3 * cn + 1];
    g.c = conics[3 * cn + 2];
    g.o = opac[n];
    g.thr = g.o >= T(kAlphaMin) ? footprint_thr(g.o) : T(-1);
    g.x0 = rect[4 * cn];
    g.x1 = rect[4 * cn + 1];
    g.y0 = rect[4 * cn + 2];
    g.y1 = rect[4 * cn + 3];
    for (int ch = 0; ch < CH; ++ch) g.f[ch] = feats[cn * CH + ch];
  }
}

// A tile is TS x TS pixels (TS = 8 or 16). An intersection (tile, Gaussian) is evaluated row by
// row over the rows of the Gaussian's rectangle inside the tile; a row's TS pixels are the SIMD
// lanes (one AVX-512 vector of floats for TS = 16). Forward and backward compute sigma with the
// same expression, so they take the same in/out decisions bit for bit.
// Tile lists visit the Gaussian records (and write the per-intersection records) in depth order,
// i.e. at random: prefetching a few entries ahead hides most of the cache misses (measured: -17 %
// forward, -25 % backward time at 50k Gaussians, 256x192).
constexpr int kPrefetch = 4;

// 0, read at run time (a volatile load), so the compiler cannot fold it: the `zero` of opaque().
inline uint64_t runtime_zero() {
  volatile uint64_t z = 0;
  return z;
}

// x, with its bits XORed with `zero` (runtime_zero()): the compiler then no longer sees that a
// weight built from selects is 0 on inactive lanes, nor what the value was made of. Without it gcc turns
// `acc += w * f` into masked stores behind a branch on "any lane active", a branch that
// mispredicts row after row (measured: forward -20 % with the plain update, demo fit's model).
template <typename T>
inline T opaque(T x, uint64_t zero) {
  using U = std::conditional_t<sizeof(T) == 4, uint32_t, uint64_t>;
  U b;
  std::memcpy(&b, &x, sizeof(T));
  b ^= U(zero);
  std::memcpy(&x, &b, sizeof(T));
  return x;
}

// The sum of a row's TS lanes as a fixed halving tree (lane j + lane j + w for w = TS/2, ..., 1).
// Every step is element-wise, so any vector width gives the same result; an `omp simd reduction`
// would sum in an order set by the vector width (8 lanes for AVX2, 16 for AVX-512), and the x86-64
// builds of the kernel would then disagree in the last bits. The halves are GCC vector values, so
// the tree stays in registers: written as loops over a stack array, each level's narrower loads of
// the previous level's wider stores missed store-to-load forwarding (measured: the backward's nine
// sums per intersection took ~110 ns, more than its rows).
template <typename T, int W>
struct HalvingTree {
  typedef T V __attribute__((vector_size(W * sizeof(T))));
  typedef T H __attribute__((vector_size(W / 2 * sizeof(T))));
  static T sum(const V& v) {
    H lo, hi;
    std::memcpy(&lo, &v, sizeof(H));
    std::memcpy(&hi, reinterpret_cast<const char*>(&v) + sizeof(H), sizeof(H));
    return HalvingTree<T, W / 2>::sum(lo + hi);
  }
};
template <typename T>
struct HalvingTree<T, 2> {
  typedef T V __attribute__((vector_size(2 * sizeof(T))));
  static T sum(const V& v) { return v[0] + v[1]; }
};

template <typename T, int TS>
inline T lane_sum(const T* a) {
  static_assert(TS >= 2 && (TS & (TS - 1)) == 0, "TS must be a power of two");
  typename HalvingTree<T, TS>::V v;
  std::memcpy(&v, a, sizeof(v));
  return HalvingTree<T, TS>::sum(v);
}

// The rows [r0, r1] of an entry (tile, Gaussian) without the rows at either end where no pixel centre
// of the Gaussian's columns in the tile lies inside its footprint (sigma <= thr); r0 > r1 when no row
// is left. Those rows change nothing in either pass (alpha 0), but the bounding box of a thin tilted
// Gaussian holds many of them: at lund's 1024 px, a fifth of the rows evaluated and 15 % of the
// entries (forward 23 %, backward 26 % faster without them). A row is dropped only when the minimum
// of sigma over its segment, in closed form, exceeds thr by a margin far above the rounding of the
// lanes' own sigma (1e-5 of the terms' magnitude): the lanes' in/out decisions, and so both passes'
// results, are unchanged bit for bit. (ha, hb, hc, thr: sigma * log2(e), as the passes compute them.)
template <typename T, int TS>
inline void trim_rows(int X0, int Y0, int gx0, int gx1, T u, T v, T ha, T hb, T hc, T thr, int& r0, int& r1) {
  const int jl = std::max(gx0 - X0, 0), jh = std::min(gx1 - X0, TS - 1);
  if (!(ha > T(0)) || jl > jh) return;
  const T xl = T(X0 + jl) + T(0.5) - u, xh = T(X0 + jh) + T(0.5) - u;
  const T xs = -hb / (T(2) * ha);  // the minimising dx per unit of dy
  const T m = std::max(std::abs(xl), std::abs(xh));
  auto empty = [&](int r) {
    const T dy = T(Y0 + r) + T(0.5) - v;
    const T cy = hc * dy * dy, by = hb * dy;
    const T dx = clampv(xs * dy, xl, xh);
    const T low = (ha * dx + by) * dx + cy;
    const T mag = ha * m * m + std::abs(by) * m + cy;
    return low > thr + T(1e-5) * mag;  // (false for NaN: kept)
  };
  while (r0 <= r1 && empty(r0)) ++r0;
  while (r1 >= r0 && empty(r1)) --r1;
}

// MED: also write median_out [C*H*W], the last feature channel (the depth) of the Gaussian at which
// a pixel's transmittance first falls to 0.5 or below (0 where it never does): the median depth,
// which lies on a surface where the expected depth (sum w z / alpha) is pulled towards the camera
// by the Gaussians spread along it. Its own instantiation: the training path pays nothing for it.
template <typename T, int TS, int CH, bool MED = false>
void raster_fwd(int C, int N, int W, int H, const GaussPix<T, CH>* gp, const int64_t* tile_off,
                const Isect* isect, const int64_t* gauss_off,
                const uint8_t* cmask, T* out, T* alpha_out, T* tfinal, int32_t* last_out,
                T* contrib, int nthreads, T* median_out = nullptr) {
  PhaseTimer timer_("raster_fwd");
  constexpr int P = TS * TS;
  const int tw = (W + TS - 1) / TS, th = (H + TS - 1) / TS;
  const int64_t TT = int64_t(tw) * th;
  const int64_t M = tile_off[C * TT];
  // one contribution record per intersection, every one written below (no initialisation needed)
  std::unique_ptr<T[]> crec(new T[std::max<int64_t>(M, 1)]);
  int64_t rows_done = 0;  // statistics for SGPOR_KERNEL_PROFILE and the benchmark
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1) reduction(+ : rows_done)
  for (int64_t ct = 0; ct < C * TT; ++ct) {
    const int c = int(ct / TT);
    const int64_t t = ct % TT;
    const int X0 = int(t % tw) * TS, Y0 = int(t / tw) * TS;
    const GaussPix<T, CH>* g_cam = gp + int64_t(c) * N;
    alignas(64) T Tr[P];  // transmittance; negative once the pixel stopped (or is off the image)
    // The median pass (one channel) accumulates a second channel of zeros: with one, gcc turned the
    // row loop's stores into masked stores behind a branch per vector, mispredicted row after row
    // (the pass took twice as long: lund's 1024 px views, 0.38 -> 0.19 s). Its outputs (median,
    // alpha, contributions) are unchanged. Since the kernel's multiply-adds are written out (fmadd),
    // the plain one-channel pass is as fast as the others without it (lund 1024: 159-172 ms against
    // 157-179 for two to four channels), and the median pass gains about 10 % from it.
    constexpr int CA = (MED && CH < 2) ? 2 : CH;
    alignas(64) T acc[CA][P];
    alignas(64) T msk[P];  // 1 where the pixel counts for contrib
    alignas(64) int32_t last[P];  // 1 + index (in the tile list) of the last contribution
    alignas(64) T med[MED ? P : 1];  // MED: the median depth so far
    alignas(64) T px[TS];
    alignas(64) int32_t col[TS];
    alignas(64) T thrl[TS];  // per entry: the sigma*log2(e) threshold, or -big outside [x0, x1]
    alignas(64) T csum[TS];
    bool live[TS];  // whether a row still has an unsaturated pixel (refreshed every 8 entries)
    for (int j = 0; j < TS; ++j) {
      px[j] = T(X0 + j) + T(0.5);
      col[j] = X0 + j;
    }
    for (int r = 0; r < TS; ++r) {
      live[r] = Y0 + r < H;
      for (int j = 0; j < TS; ++j) {
        const int p = r * TS + j;
        const bool inside = (X0 + j < W) && (Y0 + r < H);
        Tr[p] = inside ? T(1) : T(-1);
        msk[p] = (inside && (!cmask || cmask[(int64_t(c) * H + Y0 + r) * W + X0 + j])) ? T(1) : T(0);
        last[p] = 0;
        if constexpr (MED) med[p] = 0;
        for (int ch = 0; ch < CA; ++ch) acc[ch][p] = 0;
      }
    }
    const int64_t s0 = tile_off[ct], s1 = tile_off[ct + 1];
    int64_t s = s0;
    const uint64_t zero = runtime_zero();  // see opaque()
    for (; s < s1; ++s) {
      // the Gaussian records are read in depth order, i.e. at random: fetch a few entries ahead
      if (s + kPrefetch < s1) {
        __builtin_prefetch(&g_cam[isect[s + kPrefetch].gid]);
        __builtin_prefetch(&crec[isect[s + kPrefetch].gen], 1);
      }
      const GaussPix<T, CH>& g = g_cam[isect[s].gid];
      const int kk = int(s - s0) + 1;
      int rt0 = std::max(g.y0 - Y0, 0), rt1 = std::min(g.y1 - Y0, TS - 1);
      const T l2 = T(kLog2e);
      const T ha = T(0.5) * g.a * l2, hb = g.b * l2, hc = T(0.5) * g.c * l2, u = g.u, o = g.o;
      const T thr = g.thr * l2;
      const int gx0 = g.x0, gx1 = g.x1;  // (& not &&: a branch-free loop that vectorises)
      trim_rows<T, TS>(X0, Y0, gx0, gx1, u, g.v, ha, hb, hc, thr, rt0, rt1);
      const int r0 = rt0, r1 = rt1;  // (const: the row loops vectorise as before)
      if (r0 > r1) {  // no pixel of the tile inside the footprint
        crec[isect[s].gen] = 0;
        continue;
      }
#pragma omp simd
      for (int j = 0; j < TS; ++j) thrl[j] = ((col[j] >= gx0) & (col[j] <= gx1)) ? thr : T(-1e30);
      T f[CA] = {};
      for (int ch = 0; ch < CH; ++ch) f[ch] = g.f[ch];
      for (int j = 0; j < TS; ++j) csum[j] = 0;
      for (int r = r0; r <= r1; ++r) {
        if (!live[r]) continue;
        ++rows_done;
        const T dy = T(Y0 + r) + T(0.5) - g.v;
        const T cy = hc * dy * dy, by = hb * dy;
        const int p0 = r * TS;
#pragma omp simd
        for (int j = 0; j < TS; ++j) {
          const int p = p0 + j;
          const T dx = px[j] - u;
          const T sig2 = fmadd(fmadd(ha, dx, by), dx, cy);  // sigma * log2(e)
          const T al = std::min(T(kAlphaMax), o * exp2_kernel(-std::min(sig2, T(kSigmaLog2Max))));
          const T Tcur = Tr[p];
          const bool in = (sig2 <= thrl[j]) & (al >= T(kAlphaMin)) & (Tcur > T(0));
          const T a0 = in ? al : T(0);
          const T tT = Tcur * (T(1) - a0);
          const bool stop = in & (tT < T(kTMin));  // stop before adding this Gaussian
          const T a = stop ? T(0) : a0;
          const T w = opaque(a * Tcur, zero);
          for (int ch = 0; ch < CA; ++ch) acc[ch][p] = fmadd(w, f[ch], acc[ch][p]);
          Tr[p] = stop ? -Tcur : tT;
          last[p] = a > T(0) ? kk : last[p];
          if constexpr (MED) med[p] = (a > T(0)) & (Tcur > T(0.5)) & (tT <= T(0.5)) ? f[CH - 1] : med[p];
          csum[j] = fmadd(w, msk[p], csum[j]);
        }
      }
      crec[isect[s].gen] = lane_sum<T, TS>(csum);
      if ((kk & 7) == 0) {
        bool any = false;
        for (int r = 0; r < TS; ++r) {
          T m = 0;
#pragma omp simd reduction(max : m)
          for (int j = 0; j < TS; ++j) m = std::max(m, Tr[r * TS + j]);
          live[r] = live[r] && m > T(0);
          any = any || live[r];
        }
        if (!any) {  // every pixel of the tile stopped
          ++s;
          break;
        }
      }
    }
    for (; s < s1; ++s) crec[isect[s].gen] = 0;
    for (int r = 0; r < TS && Y0 + r < H; ++r)
      for (int j = 0; j < TS && X0 + j < W; ++j) {
        const int p = r * TS + j;
        const int64_t pix = (int64_t(c) * H + Y0 + r) * W + X0 + j;
        for (int ch = 0; ch < CH; ++ch) out[pix * CH + ch] = acc[ch][p];
        const T tf = std::abs(Tr[p]);
        alpha_out[pix] = T(1) - tf;
        tfinal[pix] = tf;
        last_out[pix] = last[p];
        if constexpr (MED) median_out[pix] = med[p];
      }
  }
  if (profiling())
    std::fprintf(stderr, "[sgpor] fwd: %lld intersections, %lld rows of %d px evaluated\n",
                 (long long)M, (long long)rows_done, TS);
  stats_set(0, M, rows_done * TS);
  // contrib: per Gaussian, its records in generation order
  const int64_t CN = int64_t(C) * N;
#pragma omp parallel for num_threads(par_threads(nthreads, 0.004 * double(M + N * C))) schedule(static)
  for (int64_t cn = 0; cn < CN; ++cn) {
    T sum = 0;
    for (int64_t k = gauss_off[cn]; k < gauss_off[cn + 1]; ++k) sum += crec[k];
    contrib[cn] = sum;
  }
}

template <typename T, int TS, int CH>
void raster_bwd(int C, int N, int W, int H, const GaussPix<T, CH>* gp, const int64_t* tile_off,
                const Isect* isect, const int64_t* gauss_off,
                const T* tfinal, const int32_t* last_in, const T* g_out, const T* g_alpha,
                T* g_means2d, T* g_conics, T* g_feats, T* g_opac, int nthreads,
                const uint8_t* train = nullptr) {
  PhaseTimer timer_("raster_bwd");
  constexpr int P = TS * TS;
  const int tw = (W + TS - 1) / TS, th = (H + TS - 1) / TS;
  const int64_t TT = int64_t(tw) * th;
  const int64_t M = tile_off[C * TT];
  constexpr int R = 6 + CH;  // gradient record: d/du, d/dv, d/da, d/db, d/dc, d/do, d/df[CH]
  // one record per intersection, every one written below (no initialisation needed)
  std::unique_ptr<T[]> rec(new T[std::max<int64_t>(M, 1) * R]);
  int64_t rows_done = 0;  // statistics for SGPOR_KERNEL_PROFILE and the benchmark
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 1) reduction(+ : rows_done)
  for (int64_t ct = 0; ct < C * TT; ++ct) {
    const int c = int(ct / TT);
    const int64_t t = ct % TT;
    const int X0 = int(t % tw) * TS, Y0 = int(t / tw) * TS;
    const GaussPix<T, CH>* g_cam = gp + int64_t(c) * N;
    alignas(64) T Tc[P];   // transmittance behind the current entry
    alignas(64) T D1[P];   // sum over channels of dL/dC * (colour accumulated behind)
    alignas(64) T dC[CH][P];
    alignas(64) T dAf[P];  // dL/dA * T_final
    alignas(64) int32_t last[P];
    alignas(64) T px[TS];
    alignas(64) int32_t col[TS];
    alignas(64) T thrl[TS];
    // per-column sums over the rows: dsig, dsig dy, (dsig dx^2, dsig dx dy: filled per entry),
    // dsig dy^2, d/do, d/df[CH]; dsig = dL/dsigma
    constexpr int NA = 6 + CH;
    alignas(64) T acc[NA][TS];
    int rlast[TS];  // entries at or after rlast[r] touch no pixel of row r
    int kmax = 0;
    for (int j = 0; j < TS; ++j) {
      px[j] = T(X0 + j) + T(0.5);
      col[j] = X0 + j;
    }
    for (int r = 0; r < TS; ++r) {
      int m = 0;
      for (int j = 0; j < TS; ++j) {
        const int p = r * TS + j;
        const bool inside = (X0 + j < W) && (Y0 + r < H);
        const int64_t pix = (int64_t(c) * H + Y0 + r) * W + X0 + j;
        for (int ch = 0; ch < CH; ++ch) dC[ch][p] = inside ? g_out[pix * CH + ch] : T(0);
        const T tf = inside ? tfinal[pix] : T(1);
        Tc[p] = tf;
        D1[p] = 0;
        dAf[p] = inside ? g_alpha[pix] * tf : T(0);
        last[p] = inside ? last_in[pix] : 0;
        m = std::max(m, last[p]);
      }
      rlast[r] = m;
      kmax = std::max(kmax, m);
    }
    const int64_t s0 = tile_off[ct], s1 = tile_off[ct + 1];
    // With a grad_mask, the entries in front of the frontmost trained one need no pass: an entry's
    // gradient depends only on itself and the entries behind it (a tile with no trained entry at
    // all is skipped whole). Their records are zero, as those behind the last contributing entry.
    int64_t s_lo = s0;
    if (train != nullptr) {
      s_lo = s0 + kmax;
      for (int64_t s = s0; s < s0 + kmax; ++s)
        if (train[isect[s].gid]) {
          s_lo = s;
          break;
        }
    }
    auto zero_records = [&](int64_t from, int64_t to) {
      for (int64_t s = from; s < to; ++s) {
        T* rr = &rec[int64_t(isect[s].gen) * R];
        for (int i = 0; i < R; ++i) rr[i] = 0;
      }
    };
    zero_records(s0, s_lo);
    zero_records(s0 + kmax, s1);
    for (int64_t s = s0 + kmax - 1; s >= s_lo; --s) {  // back to front
      if (s - kPrefetch >= s_lo) {
        __builtin_prefetch(&g_cam[isect[s - kPrefetch].gid]);
        __builtin_prefetch(&rec[int64_t(isect[s - kPrefetch].gen) * R], 1);
      }
      const GaussPix<T, CH>& g = g_cam[isect[s].gid];
      const int kk = int(s - s0);  // entries with kk < last[p] contributed where inside
      int rt0 = std::max(g.y0 - Y0, 0), rt1 = std::min(g.y1 - Y0, TS - 1);
      const T l2 = T(kLog2e);
      const T ha = T(0.5) * g.a * l2, hb = g.b * l2, hc = T(0.5) * g.c * l2, u = g.u, o = g.o;
      const T thr = g.thr * l2;
      const int gx0 = g.x0, gx1 = g.x1;  // (& not &&: a branch-free loop that vectorises)
      trim_rows<T, TS>(X0, Y0, gx0, gx1, u, g.v, ha, hb, hc, thr, rt0, rt1);
      const int r0 = rt0, r1 = rt1;  // (const: the row loops vectorise as before)
      if (r0 > r1) {  // no pixel of the tile inside the footprint: no gradient, nothing carried
        zero_records(s, s + 1);
        continue;
      }
#pragma omp simd
      for (int j = 0; j < TS; ++j) thrl[j] = ((col[j] >= gx0) & (col[j] <= gx1)) ? thr : T(-1e30);
      T f[CH];
      for (int ch = 0; ch < CH; ++ch) f[ch] = g.f[ch];
      // The entry's rows in this tile. Without gradients (a Gaussian outside the grad_mask: the
      // finetune trains a tenth of them) only what the Gaussians in front need is carried, the
      // transmittance and D1, by the same expressions: the trained Gaussians' gradients are bit
      // for bit those of an unmasked pass.
      auto rows_pass = [&](auto with_grad) {
        constexpr bool kGrad = decltype(with_grad)::value;
        for (int r = r0; r <= r1; ++r) {
          if (kk >= rlast[r]) continue;
          ++rows_done;
          const T dy = T(Y0 + r) + T(0.5) - g.v;
          const T cy = hc * dy * dy, by = hb * dy;
          const int p0 = r * TS;
#pragma omp simd
          for (int j = 0; j < TS; ++j) {
            const int p = p0 + j;
            const T dx = px[j] - u;
            const T sig2 = fmadd(fmadd(ha, dx, by), dx, cy);  // as in the forward
            const T G = exp2_kernel(-std::min(sig2, T(kSigmaLog2Max)));
            const T oG = o * G;
            const T al = std::min(T(kAlphaMax), oG);
            const bool in = (sig2 <= thrl[j]) & (al >= T(kAlphaMin)) & (kk < last[p]);
            const T a = in ? al : T(0);
            const T inv_om = T(1) / (T(1) - a);
            const T Tcur = Tc[p];
            const T Tb = Tcur * inv_om;  // transmittance in front of this Gaussian
            const T w = a * Tb;
            T F = 0;
            for (int ch = 0; ch < CH; ++ch) F = fmadd(dC[ch][p], f[ch], F);
            if constexpr (kGrad) {
              // dL/dalpha = (sum_ch dC (T_behind f - S_behind) + dL/dA T_final) / (1 - alpha)
              const T dal = inv_om * (fmadd(Tcur, F, dAf[p]) - D1[p]);
              D1[p] = fmadd(w, F, D1[p]);
              for (int ch = 0; ch < CH; ++ch) acc[6 + ch][j] = fmadd(w, dC[ch][p], acc[6 + ch][j]);
              Tc[p] = Tb;
              const bool live = in & (oG <= T(kAlphaMax));  // a clamped alpha passes no gradient
              const T dsig = live ? -a * dal : T(0);
              acc[5][j] += live ? G * dal : T(0);
              // dx is constant down a column: the dx factors are applied once per entry below
              const T t1 = dsig * dy;
              acc[0][j] += dsig;
              acc[1][j] += t1;
              acc[4][j] = fmadd(t1, dy, acc[4][j]);
            } else {
              D1[p] = fmadd(w, F, D1[p]);
              Tc[p] = Tb;
            }
          }
        }
      };
      if (train != nullptr && !train[isect[s].gid]) {
        rows_pass(std::false_type{});
        zero_records(s, s + 1);
        continue;
      }
      for (int i = 0; i < NA; ++i)
        for (int j = 0; j < TS; ++j) acc[i][j] = 0;
      rows_pass(std::true_type{});
      // the dx factors (dx is constant down a column; -ffp-contract=off: none fuses into lane_sum)
#pragma omp simd
      for (int j = 0; j < TS; ++j) {
        const T dx = px[j] - u;
        acc[2][j] = acc[0][j] * dx * dx;
        acc[3][j] = acc[1][j] * dx;
        acc[0][j] = acc[0][j] * dx;
      }
      T sum[NA];
      for (int i = 0; i < NA; ++i) sum[i] = lane_sum<T, TS>(acc[i]);
      T* rr = &rec[int64_t(isect[s].gen) * R];
      // sigma = 0.5 a dx^2 + b dx dy + 0.5 c dy^2 with dx = px - u, dy = py - v
      const T ca = g.a, cb = g.b, cc = g.c;
      rr[0] = -(ca * sum[0] + cb * sum[1]);
      rr[1] = -(cb * sum[0] + cc * sum[1]);
      rr[2] = T(0.5) * sum[2];
      rr[3] = sum[3];
      rr[4] = T(0.5) * sum[4];
      for (int i = 5; i < R; ++i) rr[i] = sum[i];
    }
  }
  if (profiling())
    std::fprintf(stderr, "[sgpor] bwd: %lld intersections, %lld rows of %d px evaluated\n",
                 (long long)M, (long long)rows_done, TS);
  stats_set(1, M, rows_done * TS);
  // Per-Gaussian reduction in generation order; opacity summed over cameras in camera order.
#pragma omp parallel for num_threads(par_threads(nthreads, 0.01 * double(M + N * C))) schedule(static)
  for (int64_t n = 0; n < N; ++n) {
    T go = 0;
    for (int c = 0; c < C; ++c) {
      const int64_t cn = int64_t(c) * N + n;
      T sum[R];
      for (int i = 0; i < R; ++i) sum[i] = 0;
      for (int64_t k = gauss_off[cn]; k < gauss_off[cn + 1]; ++k) {
        const T* rr = &rec[k * R];
        for (int i = 0; i < R; ++i) sum[i] += rr[i];
      }
      g_means2d[2 * cn] = sum[0];
      g_means2d[2 * cn + 1] = sum[1];
      for (int i = 0; i < 3; ++i) g_conics[3 * cn + i] = sum[2 + i];
      for (int ch = 0; ch < CH; ++ch) g_feats[cn * CH + ch] = sum[6 + ch];
      go += sum[5];
    }
    g_opac[n] = go;
  }
}

}  // namespace sgpor
