// Fused SSIM of the trainer's photometric loss, for the CPU: raster.cpp exports it.
//
// The definition is kornia.metrics.ssim(x, y, 11)'s (an 11-tap Gaussian window with sigma 1.5,
// reflect padding, C1 = 0.01^2, C2 = 0.03^2, eps 1e-12), as sgpor_pipeline/gaussians/train.py's
// torch version computes it. Forward: the five local moments (x, y, x^2, y^2, xy, each blurred
// separably), the SSIM map and its plain or weighted sum. Backward: the map's gradient with
// respect to x, through the adjoint of the blur. Planes and rows go to OpenMP threads; sums are
// kept per row in double and added in a fixed order, so results do not depend on the thread count.
// Images are [C,H,W] with H, W > 5 (reflect padding); the caller checks.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "fmadd.h"

namespace sgpor {
namespace ssim {

constexpr int kPad = 5;
constexpr int kTaps = 2 * kPad + 1;
constexpr double kC1 = 0.01 * 0.01;
constexpr double kC2 = 0.03 * 0.03;
constexpr double kEps = 1e-12;

template <typename T>
void window(T g[kTaps]) {
  double v[kTaps], s = 0.0;
  for (int k = 0; k < kTaps; ++k) {
    const double x = k - kPad;
    v[k] = std::exp(-(x * x) / (2.0 * 1.5 * 1.5));
    s += v[k];
  }
  for (int k = 0; k < kTaps; ++k) g[k] = T(v[k] / s);
}

inline int reflect(int i, int n) { return i < 0 ? -i : (i >= n ? 2 * (n - 1) - i : i); }

// The SSIM map's factors at one pixel, s = A B / (C D + eps), from the five moments of the
// forward's output (moment k of the pixel at mom[k * cplane + i]).
template <typename T>
struct Terms {
  T mu1, mu2, A, B, C, D, den, s;
  Terms(const T* mom, int64_t cplane, int64_t i) {
    mu1 = mom[i];
    mu2 = mom[cplane + i];
    A = T(2) * mu1 * mu2 + T(kC1);
    B = T(2) * (mom[4 * cplane + i] - mu1 * mu2) + T(kC2);
    C = mu1 * mu1 + mu2 * mu2 + T(kC1);
    D = (mom[2 * cplane + i] - mu1 * mu1) + (mom[3 * cplane + i] - mu2 * mu2) + T(kC2);
    den = C * D + T(kEps);
    s = A * B / den;
  }
};

// dst = the separable blur of src (H x W), reflect-padded; row: scratch of W + 2 kPad, tmp: H x W.
template <typename T>
void blur_plane(const T* src, T* dst, int H, int W, const T* g, T* row, T* tmp) {
  for (int r = 0; r < H; ++r) {
    const T* s = src + int64_t(r) * W;
    // the interior copied, only the borders reflected (reflect() per element was most of the blur)
    std::copy(s, s + W, row + kPad);
    for (int j = 0; j < kPad; ++j) {
      row[j] = s[reflect(j - kPad, W)];
      row[W + kPad + j] = s[reflect(W + j, W)];
    }
    T* t = tmp + int64_t(r) * W;
    for (int j = 0; j < W; ++j) t[j] = row[j] * g[0];
    for (int k = 1; k < kTaps; ++k) {
      const T gk = g[k];
      const T* rk = row + k;
#pragma omp simd
      for (int j = 0; j < W; ++j) t[j] = fmadd(rk[j], gk, t[j]);
    }
  }
  for (int i = 0; i < H; ++i) {
    T* d = dst + int64_t(i) * W;
    const T* t0 = tmp + int64_t(reflect(i - kPad, H)) * W;
    for (int j = 0; j < W; ++j) d[j] = t0[j] * g[0];
    for (int k = 1; k < kTaps; ++k) {
      const T gk = g[k];
      const T* tk = tmp + int64_t(reflect(i + k - kPad, H)) * W;
#pragma omp simd
      for (int j = 0; j < W; ++j) d[j] = fmadd(tk[j], gk, d[j]);
    }
  }
}

// dst = the adjoint of blur_plane applied to src; rowpad: W + 2 kPad, tmp: (H + 2 kPad) x W.
template <typename T>
void blur_adjoint_plane(const T* src, T* dst, int H, int W, const T* g, T* rowpad, T* tmp) {
  // the vertical pass' adjoint into padded rows, then the padding folded back (reflect)
  std::fill(tmp, tmp + int64_t(H + 2 * kPad) * W, T(0));
  for (int i = 0; i < H; ++i) {
    const T* s = src + int64_t(i) * W;
    for (int k = 0; k < kTaps; ++k) {
      const T gk = g[k];
      T* t = tmp + int64_t(i + k) * W;
#pragma omp simd
      for (int j = 0; j < W; ++j) t[j] = fmadd(s[j], gk, t[j]);
    }
  }
  for (int p = 0; p < kPad; ++p) {  // padded row p is row kPad - p; padded row H + kPad + q is H - 2 - q
    T* a = tmp + int64_t(kPad + (kPad - p)) * W;
    const T* b = tmp + int64_t(p) * W;
    for (int j = 0; j < W; ++j) a[j] += b[j];
    T* c = tmp + int64_t(kPad + H - 2 - p) * W;
    const T* d = tmp + int64_t(H + kPad + p) * W;
    for (int j = 0; j < W; ++j) c[j] += d[j];
  }
  // the horizontal pass' adjoint, row by row
  for (int r = 0; r < H; ++r) {
    const T* t = tmp + int64_t(r + kPad) * W;
    std::fill(rowpad, rowpad + W + 2 * kPad, T(0));
    for (int k = 0; k < kTaps; ++k) {
      const T gk = g[k];
      T* a = rowpad + k;
#pragma omp simd
      for (int j = 0; j < W; ++j) a[j] = fmadd(t[j], gk, a[j]);
    }
    T* d = dst + int64_t(r) * W;
    for (int j = 0; j < W; ++j) d[j] = rowpad[j + kPad];
    for (int p = 0; p < kPad; ++p) {
      d[kPad - p] += rowpad[p];
      d[W - 2 - p] += rowpad[W + kPad + p];
    }
  }
}

// Forward. x, y: [C,H,W]; wmap: [H,W] weights or null (plain sum); mom: [5C,H,W] output (the
// moments mu_x, mu_y, E[x^2], E[y^2], E[xy], channel-major within each); returns the sum of the
// SSIM map (times wmap per pixel when given) over all channels and pixels.
template <typename T>
double forward(int C, int H, int W, const T* x, const T* y, const T* wmap, T* mom, int nthreads) {
  T g[kTaps];
  window(g);
  const int64_t plane = int64_t(H) * W;
  const int P = 5 * C;
#pragma omp parallel num_threads(nthreads)
  {
    std::vector<T> src(plane), tmp(plane), row(W + 2 * kPad);
#pragma omp for schedule(static)
    for (int q = 0; q < P; ++q) {
      const int kind = q / C, c = q % C;
      const T* a = (kind == 0 || kind == 2 || kind == 4) ? x + c * plane : y + c * plane;
      const T* b = kind == 4 ? y + c * plane : a;
      const T* in = a;
      if (kind >= 2) {
        for (int64_t i = 0; i < plane; ++i) src[i] = a[i] * b[i];
        in = src.data();
      }
      blur_plane(in, mom + int64_t(q) * plane, H, W, g, row.data(), tmp.data());
    }
  }
  std::vector<double> rows(int64_t(C) * H, 0.0);
  const int64_t cplane = C * plane;
#pragma omp parallel num_threads(nthreads)
  {
    std::vector<T> smap(W);  // a row of the map, vectorised; then summed in order, in double
#pragma omp for schedule(static)
    for (int cr = 0; cr < C * H; ++cr) {
      const int64_t o = int64_t(cr) * W;  // channel cr / H, row cr % H
      const T* wr = wmap ? wmap + int64_t(cr % H) * W : nullptr;
      T* sm = smap.data();
#pragma omp simd
      for (int j = 0; j < W; ++j) sm[j] = Terms<T>(mom, cplane, o + j).s;
      double acc = 0.0;
      for (int j = 0; j < W; ++j) acc += wr ? double(sm[j]) * double(wr[j]) : double(sm[j]);
      rows[cr] = acc;
    }
  }
  double total = 0.0;
  for (double v : rows) total += v;
  return total;
}

// Backward: dx [C,H,W] = d(sum)/dx times scale (times wmap per pixel when given), from the
// forward's moments.
template <typename T>
void backward(int C, int H, int W, const T* x, const T* y, const T* mom, const T* wmap, double scale,
              T* dx, int nthreads) {
  T g[kTaps];
  window(g);
  const int64_t plane = int64_t(H) * W;
  std::vector<T> maps(3 * C * plane), adj(3 * C * plane);
  const T sc = T(scale);
  const int64_t cplane = C * plane;
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int cr = 0; cr < C * H; ++cr) {
    const int64_t o = int64_t(cr) * W;  // channel cr / H, row cr % H
    const T* wr = wmap ? wmap + int64_t(cr % H) * W : nullptr;
    T *g1 = maps.data() + o, *g11 = maps.data() + cplane + o, *g12 = maps.data() + 2 * cplane + o;
#pragma omp simd
    for (int j = 0; j < W; ++j) {
      const Terms<T> t(mom, cplane, o + j);
      const T dA = t.B / t.den, dB = t.A / t.den, dC = -t.s * t.D / t.den, dD = -t.s * t.C / t.den;
      const T w = wr ? sc * wr[j] : sc;
      g1[j] = ((T(2) * t.mu2) * (dA - dB) + (T(2) * t.mu1) * (dC - dD)) * w;
      g11[j] = dD * w;
      g12[j] = T(2) * dB * w;
    }
  }
#pragma omp parallel num_threads(nthreads)
  {
    std::vector<T> tmp(int64_t(H + 2 * kPad) * W), rowpad(W + 2 * kPad);
#pragma omp for schedule(static)
    for (int q = 0; q < 3 * C; ++q)
      blur_adjoint_plane(maps.data() + int64_t(q) * plane, adj.data() + int64_t(q) * plane, H, W, g,
                         rowpad.data(), tmp.data());
  }
#pragma omp parallel for schedule(static) num_threads(nthreads)
  for (int cr = 0; cr < C * H; ++cr) {
    const int64_t o = int64_t(cr) * W;
    const T *gm = adj.data() + o, *g11 = adj.data() + cplane + o, *g12 = adj.data() + 2 * cplane + o;
    for (int j = 0; j < W; ++j) dx[o + j] = gm[j] + T(2) * x[o + j] * g11[j] + y[o + j] * g12[j];
  }
}

}  // namespace ssim
}  // namespace sgpor
