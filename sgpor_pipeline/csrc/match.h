// Masked block matching for SBM's re-ranking (sgpor_pipeline/removal/sbm.py): raster.cpp exports it.
//
// For each target t and each of its KC candidates j, the weighted sum of squared differences of the
// target's template (a win x win window of the current image) against the candidate's region at
// every shift (dy, dx) in [0, 2r] x [0, 2r] that is a multiple of `step` (2r a multiple of step):
//   out[t, j, a, b] = sum_{u, w, ch} mask[u, w]^2 * (region[a step + u, b step + w, ch] - templ[u, w, ch])^2,
// a, b in [0, 2r / step]. step > 1 is the coarse pass of a coarse-to-fine search (sbm.py).
// cv2.matchTemplate's TM_SQDIFF with a mask (its weights are the mask squared), computed directly.
// cv2 computes it by DFT correlations of the expanded square, which is the slow part of a large
// hole's SBM (a 45 x 45 template and 9 x 9 shifts: most of the time goes to transforms and call
// overhead); here each template row is a contiguous run of 3 * win floats, and the rows with no
// weight are skipped. Images are HWC float32, 3 channels, with row strides in floats. Targets go to
// OpenMP threads; each writes its own rows of out, so results do not depend on the thread count.
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <limits>
#include <type_traits>
#include <vector>

namespace sgpor {
namespace match {

constexpr int kLanes = 16;
// 16 floats: one AVX-512 register, two AVX or four SSE ones (GCC lowers the vector extension to the
// -march at hand), so one source serves every kernel variant
typedef float vf __attribute__((vector_size(kLanes * sizeof(float))));

// (vectors by reference, not by value: a 64-byte vector in a signature changes the ABI without AVX-512,
// and GCC warns for the v2 and v3 builds)
inline void loadu(vf& v, const float* p) { std::memcpy(&v, p, sizeof v); }

inline float hsum(const vf& v) {
  float s = 0.0f;
  for (int l = 0; l < kLanes; ++l) s += v[l];
  return s;
}

// The one multiply-add left to gcc to fuse (the kernel is built with -ffp-contract=off, fmadd.h):
// fmadd() does not vectorise on GCC's 16-float vectors without AVX-512, and `acc += m * d * d` has one
// product that can fuse, (m * d) * d, so every FMA build fuses the same (measured: unfused, the coarse
// pass took 5-10 % longer).
#pragma GCC push_options
#pragma GCC optimize("fp-contract=fast")
// ng (<= G) outputs at shifts (dy, dx0), (dy, dx0 + st), ..., (dy, dx0 + (ng - 1) st): G accumulators
// stay in registers while each template chunk is loaded once. buf: the candidate's region, rows Lr
// floats apart, zero beyond its data, so that every read of the G lanes' windows stays inside.
template <int G>
inline void ssd_shifts(const float* buf, int64_t Lr, const float* tm, const float* m2, int Lp,
                       const int* rows, const int* lo, const int* hi, int nrows, int dy, int dx0, int st,
                       int ng, float* o) {
  vf acc[G];
  for (int g = 0; g < G; ++g) acc[g] = vf{} ;
  for (int k = 0; k < nrows; ++k) {
    const int u = rows[k];
    const float* R = buf + (dy + u) * Lr + 3 * dx0;
    const float* Tm = tm + int64_t(u) * Lp;
    const float* M = m2 + int64_t(u) * Lp;
    for (int i = lo[k]; i < hi[k]; i += kLanes) {
      vf t, m;
      loadu(t, Tm + i);
      loadu(m, M + i);
      for (int g = 0; g < G; ++g) {
        vf d;
        loadu(d, R + i + 3 * st * g);
        d -= t;
        acc[g] += m * d * d;
      }
    }
  }
  for (int g = 0; g < ng; ++g) o[g] = hsum(acc[g]);
}
#pragma GCC pop_options

// Where the candidates' regions come from: float views (padded by the caller with its sentinel), or
// 8-bit views read through a table with a validity mask, padded here (below).
struct FloatViews {
  const float* const* views;  // HWC float32
  const int64_t* vstride;     // floats per row
  // region rows (rh of rw3 floats) of candidate c = (view, y, x) into buf, rows Lr apart
  void fill(const int32_t* c, int rh, int rw3, float* buf, int64_t Lr) const {
    const int64_t vs = vstride[c[0]];
    const float* src = views[c[0]] + c[1] * vs + 3 * int64_t(c[2]);
    for (int y = 0; y < rh; ++y) std::memcpy(&buf[size_t(y) * Lr], src + y * vs, sizeof(float) * rw3);
  }
};

// 8-bit views: (y, x) of a candidate is its corner in the view padded by `pad` on every side; a pixel
// outside the view or not valid reads `sentinel`, any other lut[value]: the float padded view's value
// bit for bit (the caller's table is its own uint8 -> float32 conversion), without a float copy of
// every view (12 bytes a pixel of every view: the inpaint stage's largest per-view memory).
struct ByteViews {
  const uint8_t* const* views;   // HWC uint8, rows 3 * width apart
  const uint8_t* const* valid;   // HW, 0 = invalid
  const int32_t* height;
  const int32_t* width;
  int pad;
  const float* lut;  // [256]
  float sentinel;
  void fill(const int32_t* c, int rh, int rw3, float* buf, int64_t Lr) const {
    const int v = c[0], H = height[v], W = width[v], rw = rw3 / 3;
    const uint8_t* px = views[v];
    const uint8_t* ok = valid[v];
    for (int y = 0; y < rh; ++y) {
      float* row = &buf[size_t(y) * Lr];
      const int oy = c[1] + y - pad;
      if (oy < 0 || oy >= H) {
        std::fill(row, row + rw3, sentinel);
        continue;
      }
      for (int x = 0; x < rw; ++x) {
        const int ox = c[2] + x - pad;
        if (ox < 0 || ox >= W || !ok[int64_t(oy) * W + ox]) {
          row[3 * x] = row[3 * x + 1] = row[3 * x + 2] = sentinel;
        } else {
          const uint8_t* p = px + (int64_t(oy) * W + ox) * 3;
          row[3 * x] = lut[p[0]];
          row[3 * x + 1] = lut[p[1]];
          row[3 * x + 2] = lut[p[2]];
        }
      }
    }
  }
};

// cur: the current image, template corner of target t at (tpos[2t], tpos[2t+1]); mask: one channel,
// same layout; source: the views (FloatViews or ByteViews), candidate j's region corner at
// (cand[3(t KC + j) + 1], + 2) of view cand[3(t KC + j)] (-1: no candidate, out = +inf). The caller
// keeps every window inside its (padded) image and 2r a multiple of step.
template <class Source>
inline void masked_ssd(int T, int KC, int win, int r, int step, const float* cur, int64_t cur_stride,
                       const float* mask, int64_t mask_stride, const int32_t* tpos, const Source& source,
                       const int32_t* cand, float* out, int nthreads) {
  constexpr int G = 8;  // shifts per pass (8 accumulators + 3 temporaries: no spills with AVX)
  const int side = 2 * r / step + 1;                     // shifts per axis
  const int L = 3 * win;                                 // floats in a template row
  const int Lp = (L + kLanes - 1) / kLanes * kLanes;     // padded with zero weight
  const int groups = (side + G - 1) / G;
  const int64_t Lr = Lp + 3 * int64_t(step) * groups * G;  // region row, with room for every lane's read
  const int rh = win + 2 * r, rw3 = 3 * (win + 2 * r);   // region rows, floats per region row
#pragma omp parallel num_threads(nthreads)
  {
    std::vector<float> tm(size_t(win) * Lp), m2(size_t(win) * Lp), buf(size_t(rh) * Lr, 0.0f);
    std::vector<int> rows, lo, hi;
#pragma omp for schedule(dynamic, 4)
    for (int t = 0; t < T; ++t) {
      const int ty = tpos[2 * t], tx = tpos[2 * t + 1];
      rows.clear();
      lo.clear();
      hi.clear();
      std::fill(tm.begin(), tm.end(), 0.0f);
      std::fill(m2.begin(), m2.end(), 0.0f);
      for (int u = 0; u < win; ++u) {
        const float* crow = cur + (ty + u) * cur_stride + 3 * int64_t(tx);
        const float* mrow = mask + (ty + u) * mask_stride + tx;
        int first = L, last = -1;
        for (int w = 0; w < win; ++w) {
          const float m = mrow[w] * mrow[w];
          if (m != 0.0f) {
            first = std::min(first, 3 * w);
            last = 3 * w + 2;
          }
          for (int ch = 0; ch < 3; ++ch) {
            tm[size_t(u) * Lp + 3 * w + ch] = crow[3 * w + ch];
            m2[size_t(u) * Lp + 3 * w + ch] = m;
          }
        }
        if (last >= 0) {  // the row's chunks from the first to the last weighted value
          rows.push_back(u);
          lo.push_back(first / kLanes * kLanes);
          hi.push_back(last / kLanes * kLanes + kLanes);
        }
      }
      for (int j = 0; j < KC; ++j) {
        const int32_t* c = cand + 3 * (int64_t(t) * KC + j);
        float* o = out + (int64_t(t) * KC + j) * side * side;
        if (c[0] < 0) {
          std::fill(o, o + side * side, std::numeric_limits<float>::infinity());
          continue;
        }
        source.fill(c, rh, rw3, buf.data(), Lr);
        for (int dy = 0; dy < side; ++dy)
          for (int g = 0; g < groups; ++g) {
            const int ng = std::min(G, side - g * G);
            // as many accumulators as outputs: a fine pass's 3 shifts a row no longer pay for 8
            // (each output's sum is the same whichever G computes it)
            auto run = [&](auto n) {
              ssd_shifts<decltype(n)::value>(buf.data(), Lr, tm.data(), m2.data(), Lp, rows.data(), lo.data(),
                                             hi.data(), int(rows.size()), dy * step, g * G * step, step, ng,
                                             o + dy * side + g * G);
            };
            switch (ng) {
              case 1: run(std::integral_constant<int, 1>{}); break;
              case 2: run(std::integral_constant<int, 2>{}); break;
              case 3: run(std::integral_constant<int, 3>{}); break;
              case 4: run(std::integral_constant<int, 4>{}); break;
              case 5: run(std::integral_constant<int, 5>{}); break;
              case 6: run(std::integral_constant<int, 6>{}); break;
              case 7: run(std::integral_constant<int, 7>{}); break;
              default: run(std::integral_constant<int, G>{}); break;
            }
          }
      }
    }
  }
}

}  // namespace match
}  // namespace sgpor
