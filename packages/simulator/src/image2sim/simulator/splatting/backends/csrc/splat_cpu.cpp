// Tile-parallel CPU splatting kernel: fused inference path, forward and backward rasterisation.
//
// Contract identical to backends/reference.py: per pixel, front to back over the tile's list,
// q = d^T conic d, skip q > 3.5^2, alpha = min(0.99, o exp(-q/2)), skip alpha < 1/255,
// w = alpha T, stop after the Gaussian that drops T below t_min (1e-4 unless the caller allows a
// larger truncation: the inference option `min_transmittance`). Outputs
// image[k] = sum w v_k + (1 - sum w) bg_k and alpha = sum w.
//
// Layout and loops (see docs/splatting.md, "The compiled CPU kernel"):
// * Tiles are 16 x 16 pixels; worker threads (std::thread, joined per call: no spinning OpenMP
//   team) take whole tiles (dynamic schedule through an atomic counter).
// * Inside a tile the loop is Gaussian-outer, row-middle, chunk-inner: for one Gaussian and one
//   pixel row, `row_alpha` evaluates one chunk of pixels at once (branch-free), N pixels wide, N the
//   lanes of the target's native vector register (8 floats on AVX2, 16 on AVX-512), then the
//   transmittance update and every channel accumulation are N-lane vector ops over a channel-major
//   tile buffer acc[c][pixel]. A chunk is skipped when the Gaussian's footprint box misses it or
//   all its pixels are finished. Pixels that are finished (T < t_min) or outside the image carry
//   T = 0 and therefore add exactly nothing; a tile stops once all its pixels are done.
// * Compute type: float for float32 inputs (a Cephes-style vectorisable exp, ~1 ulp), double for
//   float64 inputs (std::exp, so float64 gradients are exactly smooth for gradcheck).
// * `row_alpha` is one out-of-line function shared by forward and backward so both make the same
//   contribute / skip decisions bit for bit.
// * The fused inference path (`render_forward`) projects (pinhole: culling Gaussians whose footprint
//   bound misses the image before their covariance is computed), sorts by depth (LSD radix sort on the
//   float bits, stable, so ties keep input order), bins into tiles (counting sort, keeps depth
//   order), packs per-Gaussian records and values contiguously in depth order, and rasterises in
//   one call: no per-frame Python or small torch ops. Optionally it first skips the Gaussians of
//   spatial blocks that a pinhole view cannot see (culling.py's conservative block test).
#include <torch/extension.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <vector>

#include "workers.h"
#if defined(__AVX__)
#include <immintrin.h>
#endif

namespace {

constexpr double kCutoff2 = 3.5 * 3.5;
constexpr double kAlphaMax = 0.99;
constexpr double kAlphaMin = 1.0 / 255.0;
constexpr int kTile = 16;          // tile edge of the vectorised kernel
constexpr int kP = kTile * kTile;  // pixels per tile (row stride kTile)

struct Grid {
  int64_t H, W, tile, ntx, nty;
  double wrap;  // 0 = no horizontal wrap
};

inline double wrap_dx(double dx, double wrap) {
  if (wrap <= 0) return dx;
  return dx - wrap * std::floor((dx + 0.5 * wrap) / wrap);
}

struct TileView {
  int64_t x0, y0, w, h;  // first pixel and the number of real (in-image) columns / rows
};

inline TileView tile_view(const Grid& g, int64_t t) {
  TileView v;
  v.x0 = (t % g.ntx) * g.tile;
  v.y0 = (t / g.ntx) * g.tile;
  v.w = std::min(g.tile, g.W - v.x0);
  v.h = std::min(g.tile, g.H - v.y0);
  return v;
}

// Largest q at which alpha = o exp(-q/2) can still reach 1/255 (tiny margin: exact test follows).
inline double q_limit(double o) {
  if (!(o >= kAlphaMin)) return -1.0;
  return std::min(kCutoff2, 2.0 * std::log(o / kAlphaMin) + 1e-4);
}

// One depth-sorted screen Gaussian, packed for the rasteriser (one 64-byte cache line).
struct alignas(64) Rec {
  double mu, mv;       // mean (pixels)
  double A, B, C;      // conic (inverse screen covariance)
  double o;            // opacity
  float ru, rv;        // footprint box half-extents (conservative: the exact q test decides)
  float qlim;          // q_limit(o) (< 0: never contributes); a prefilter only
};

inline Rec make_rec(double mu, double mv, double ru, double rv, double A, double B, double C, double o) {
  return Rec{mu, mv, A, B, C, o, static_cast<float>(ru), static_cast<float>(rv), static_cast<float>(q_limit(o))};
}

// Lane vectors of the target's native register width (64 bytes with AVX-512, 32 with AVX, 16
// otherwise): 16 / 8 / 4 floats. A tile row of 16 pixels is kTile / N such chunks. Wider-than-native
// GCC vectors are not an option: GCC 12 lowers their comparisons and selects lane by lane to scalar
// code (on AVX2 a 16-float row took ~500 cycles instead of ~50).
#if defined(__AVX512F__)
constexpr int kVecBytes = 64;
#elif defined(__AVX__)
constexpr int kVecBytes = 32;
#else
constexpr int kVecBytes = 16;
#endif
template <typename real>
struct Lanes;
template <>
struct Lanes<float> {
  static constexpr int N = kVecBytes / sizeof(float);
  typedef float V __attribute__((vector_size(kVecBytes)));
  typedef int32_t I __attribute__((vector_size(kVecBytes)));
  typedef int32_t lane_int;
};
template <>
struct Lanes<double> {
  static constexpr int N = kVecBytes / sizeof(double);
  typedef double V __attribute__((vector_size(kVecBytes)));
  typedef int64_t I __attribute__((vector_size(kVecBytes)));
  typedef int64_t lane_int;
};
static_assert(kTile % Lanes<float>::N == 0 && kTile % Lanes<double>::N == 0, "a tile row is whole chunks");

// Number of set lanes of a lane mask (lanes are 0 or -1).
template <typename I>
inline int count_lanes(const I& m) {
  int n = 0;
  for (int i = 0; i < int(sizeof(I) / sizeof(m[0])); ++i) n += m[i] != 0;
  return n;
}
#if defined(__AVX512F__)
template <>
inline int count_lanes<Lanes<float>::I>(const Lanes<float>::I& m) {
  __m512i v;
  std::memcpy(&v, &m, sizeof(v));
  return __builtin_popcount(static_cast<unsigned>(_mm512_test_epi32_mask(v, v)));
}
#elif defined(__AVX__)
template <>
inline int count_lanes<Lanes<float>::I>(const Lanes<float>::I& m) {
  __m256 v;
  std::memcpy(&v, &m, sizeof(v));
  return __builtin_popcount(static_cast<unsigned>(_mm256_movemask_ps(v)));
}
template <>
inline int count_lanes<Lanes<double>::I>(const Lanes<double>::I& m) {
  __m256d v;
  std::memcpy(&v, &m, sizeof(v));
  return __builtin_popcount(static_cast<unsigned>(_mm256_movemask_pd(v)));
}
#endif

template <typename V, typename T>
inline V vload(const T* p) {
  V v;
  std::memcpy(&v, p, sizeof(V));
  return v;
}
template <typename V, typename T>
inline void vstore(T* p, const V& v) {
  std::memcpy(p, &v, sizeof(V));
}

// exp(-q/2) for q >= 0 on one lane vector. float: Cephes expf (range reduction by ln 2, degree-6
// polynomial, about 1 ulp) in vector arithmetic; arguments below -30 (q > 60, far outside every
// footprint, where q <= 12.25) are clamped so no lane makes a denormal (and NaN maps to -30).
// double: std::exp per lane, exact, so float64 gradients are smooth for gradcheck.
inline Lanes<float>::V exp_neg_half(Lanes<float>::V q) {
  using V = Lanes<float>::V;
  using I = Lanes<float>::I;
  const V lo = V{} - 30.0f;
  V x = -0.5f * q;
  x = x > lo ? x : lo;
  const V t = x * 1.44269504088896341f;
  const V k = (t + 12582912.0f) - 12582912.0f;  // round to nearest (|t| < 2^22)
  V r = x - k * 0.693359375f;
  r = r - k * -2.12194440e-4f;
  V p = V{} + 1.9875691500E-4f;
  p = p * r + 1.3981999507E-3f;
  p = p * r + 8.3334519073E-3f;
  p = p * r + 4.1665795894E-2f;
  p = p * r + 1.6666665459E-1f;
  p = p * r + 5.0000001201E-1f;
  p = p * r * r + r + 1.0f;
  const I bits = (__builtin_convertvector(k, I) + 127) << 23;
  V scale;
  std::memcpy(&scale, &bits, sizeof(scale));
  return p * scale;
}
inline Lanes<double>::V exp_neg_half(Lanes<double>::V q) {
  Lanes<double>::V out;
  for (int i = 0; i < Lanes<double>::N; ++i) out[i] = std::exp(-0.5 * q[i]);
  return out;
}

// Alpha of one Gaussian at the N pixels of one chunk of a tile row: a[i] = min(0.99, o g) where the
// Gaussian contributes (q <= qlim and alpha >= 1/255), else exactly 0; g[i] = exp(-q/2).
// dx0 = wrapped offset (pixel centre - mean) of the row's lane 0, ch the chunk's first lane; lane
// i is dx0 + ch + i, re-wrapped once for panoramas (dx0 is in [-W/2, W/2) and ch + i < 16, real
// lanes < W). Out of line on purpose: forward and backward call the same machine code, so their
// decisions agree bit for bit.
template <typename real>
__attribute__((noinline)) void row_alpha(real A, real B, real C, real o, real qlim, real dx0, real dy,
                                         real wrap, int ch, typename Lanes<real>::V* a_out,
                                         typename Lanes<real>::V* g_out) {
  using V = typename Lanes<real>::V;
  V lane;
  for (int i = 0; i < Lanes<real>::N; ++i) lane[i] = real(ch + i);
  const V zero = V{};
  V dx = dx0 + lane;
  if (wrap > 0) dx = dx >= real(0.5) * wrap ? dx - wrap : dx;
  const V q = (A * dx + real(2) * B * dy) * dx + C * dy * dy;
  const V g = exp_neg_half(q);
  const V og = o * g;
  const V amax = zero + real(kAlphaMax);
  const V a = og < amax ? og : amax;
  *a_out = (q <= qlim) & (a >= real(kAlphaMin)) ? a : zero;
  *g_out = g;
}

// Rows [j0, j1) of tile tv that the Gaussian's footprint box touches, and the lane-0 offsets.
struct RowRange {
  int64_t j0, j1;
  double dx0, dy0;
};

inline RowRange row_range(const Grid& g, const TileView& tv, const Rec& r) {
  RowRange rr;
  rr.dy0 = tv.y0 + 0.5 - r.mv;
  // Clamp in double before the integer cast: a footprint of >= 9.2e18 px (scales ~1e18 m) overflowed
  // int64 and the Gaussian touched no row, while the torch and reference backends rendered it.
  const double h = static_cast<double>(tv.h);
  rr.j0 = static_cast<int64_t>(std::clamp(std::ceil(-r.rv - rr.dy0), 0.0, h));
  rr.j1 = static_cast<int64_t>(std::clamp(std::floor(r.rv - rr.dy0) + 1.0, 0.0, h));
  rr.dx0 = wrap_dx(tv.x0 + 0.5 - r.mu, g.wrap);
  return rr;
}

// True when no lane of the chunk [ch, ch + n) of a tile row can lie inside the Gaussian's footprint
// box (|dx| <= ru, with a pixel of slack for ru's float rounding): then every lane's q exceeds the
// 3.5-sigma cutoff and alpha is exactly 0, so skipping the chunk changes nothing. Panoramas: only
// decided while no lane of the chunk is re-wrapped (dx < W/2).
inline bool chunk_outside(double dx0, int ch, int n, float ru, double wrap) {
  const double lo = dx0 + ch, hi = lo + (n - 1);
  if (wrap > 0 && hi >= 0.5 * wrap) return false;
  return lo > ru + 1.0 || hi < -(ru + 1.0);
}

template <typename real>
using compute_t = std::conditional_t<std::is_same_v<real, double>, double, float>;

// Threads: workers.h's blocking std::thread workers, as many as torch.get_num_threads().
inline int num_workers(int64_t work_items) {
  return static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), work_items)));
}

using image2sim_workers::run_workers;

template <typename F>
void parallel_range(int64_t n, int64_t grain, const F& fn) {  // fn(begin, end)
  image2sim_workers::parallel_range(n, grain, at::get_num_threads(), fn);
}

template <typename scalar_t>
void forward_impl(const Rec* recs, const scalar_t* vals, const scalar_t* bg, int64_t D, const int64_t* offs,
                  const int64_t* ids, const Grid& g, double t_min, scalar_t* out, scalar_t* alpha_out,
                  double* t_final, int64_t* n_contrib) {
  using real = compute_t<scalar_t>;
  const int64_t n_tiles = g.ntx * g.nty;
  const int64_t HW = g.H * g.W;
  const real wrap = static_cast<real>(g.wrap);
  const real tmin = static_cast<real>(t_min);
  std::atomic<int64_t> next_tile{0};  // dynamic schedule: workers take the next tile
  run_workers(num_workers(n_tiles), [&](int) {
    using V = typename Lanes<real>::V;
    using I = typename Lanes<real>::I;
    using lane_int = typename Lanes<real>::lane_int;
    constexpr int N = Lanes<real>::N;
    alignas(64) real T[kP], asum[kP];
    alignas(64) lane_int last[kP];
    std::vector<real> acc_buf(std::max<int64_t>(D, 1) * kP);
    real* acc = acc_buf.data();
    const V zero = V{};
    for (int64_t t = next_tile++; t < n_tiles; t = next_tile++) {
      const TileView tv = tile_view(g, t);
      for (int p = 0; p < kP; ++p) {
        T[p] = (p / kTile < tv.h && p % kTile < tv.w) ? real(1) : real(0);  // padding lanes: done
        asum[p] = 0;
        last[p] = 0;
      }
      std::fill(acc, acc + D * kP, real(0));
      int64_t n_active = tv.w * tv.h;
      const int64_t begin = offs[t], end = offs[t + 1];
      for (int64_t k = begin; k < end && n_active > 0; ++k) {
        const int64_t gi = ids[k];
        if (k + 1 < end) {  // the next record and values are a cache miss away: fetch them now
          __builtin_prefetch(recs + ids[k + 1]);
          __builtin_prefetch(vals + ids[k + 1] * D);
        }
        const Rec& r = recs[gi];
        if (r.qlim < 0) continue;
        const RowRange rr = row_range(g, tv, r);
        const lane_int rank1 = static_cast<lane_int>(k - begin + 1);
        const scalar_t* v = vals + gi * D;
        for (int64_t j = rr.j0; j < rr.j1; ++j) {
          for (int ch = 0; ch < tv.w; ch += N) {
            if (chunk_outside(rr.dx0, ch, N, r.ru, g.wrap)) continue;
            const int64_t p0 = j * kTile + ch;
            real* Tr = T + p0;
            const V t0 = vload<V>(Tr);
            const I live = t0 >= tmin;
            if (count_lanes(live) == 0) continue;  // every pixel of the chunk is finished
            V a, gs;
            row_alpha<real>(r.A, r.B, r.C, r.o, r.qlim, rr.dx0, rr.dy0 + j, wrap, ch, &a, &gs);
            const V ai = live ? a : zero;
            const I hit = ai > zero;
            if (count_lanes(hit) == 0) continue;
            const V wi = ai * t0;
            const V t1 = t0 * (real(1) - ai);
            const I fin = live & (t1 < tmin);
            vstore(Tr, t1);
            vstore(asum + p0, vload<V>(asum + p0) + wi);
            lane_int* lr = last + p0;
            vstore(lr, hit ? (I{} + rank1) : vload<I>(lr));
            n_active -= count_lanes(fin);
            for (int64_t c = 0; c < D; ++c) {
              real* ac = acc + c * kP + p0;
              vstore(ac, vload<V>(ac) + wi * static_cast<real>(v[c]));
            }
          }
        }
      }
      // Output rows: channel-outer so every store run is one contiguous row of a plane.
      for (int64_t j = 0; j < tv.h; ++j) {
        const int64_t row = (tv.y0 + j) * g.W + tv.x0;
        const real* sr = asum + j * kTile;
        for (int64_t c = 0; c < D; ++c) {
          const real bc = static_cast<real>(bg[c]);
          const real* ac = acc + c * kP + j * kTile;
          scalar_t* o = out + c * HW + row;
          for (int64_t i = 0; i < tv.w; ++i) o[i] = static_cast<scalar_t>(ac[i] + (real(1) - sr[i]) * bc);
        }
        for (int64_t i = 0; i < tv.w; ++i) {
          alpha_out[row + i] = static_cast<scalar_t>(sr[i]);
          if (t_final) t_final[row + i] = static_cast<double>(T[j * kTile + i]);
          if (n_contrib) n_contrib[row + i] = last[j * kTile + i];
        }
      }
    }
  });
}

template <typename scalar_t>
void backward_impl(const Rec* recs, const scalar_t* vals, const scalar_t* bg, int64_t D, const int64_t* offs,
                   const int64_t* ids, const Grid& g, const scalar_t* alpha_out, const double* t_final,
                   const int64_t* n_contrib, const scalar_t* g_out, const scalar_t* g_alpha, scalar_t* d_mean,
                   scalar_t* d_conic, scalar_t* d_opac, scalar_t* d_vals, double* d_bg_threads) {
  using real = compute_t<scalar_t>;
  const int64_t n_tiles = g.ntx * g.nty;
  const int64_t HW = g.H * g.W;
  const real wrap = static_cast<real>(g.wrap);
  std::atomic<int64_t> next_tile{0};
  run_workers(num_workers(n_tiles), [&](int worker) {
    constexpr int N = Lanes<real>::N;
    typename Lanes<real>::V a, gs;
    std::vector<double> T(kP), Sa(kP), Ga(kP);
    std::vector<real> dv(D);
    std::vector<scalar_t> S(kP * D), G(kP * D);
    std::vector<int64_t> last(kP);
    double* d_bg = d_bg_threads + worker * D;
    for (int64_t t = next_tile++; t < n_tiles; t = next_tile++) {
      const TileView tv = tile_view(g, t);
      const int64_t begin = offs[t];
      int64_t max_last = 0;
      std::fill(last.begin(), last.end(), 0);
      std::fill(S.begin(), S.end(), scalar_t(0));
      for (int64_t j = 0; j < tv.h; ++j) {
        const int64_t row = (tv.y0 + j) * g.W + tv.x0;
        for (int64_t i = 0; i < tv.w; ++i) {
          const int64_t p = j * kTile + i;
          T[p] = t_final[row + i];
          last[p] = n_contrib[row + i];
          max_last = std::max(max_last, last[p]);
          Sa[p] = 0.0;
          // image = sum w v + (1 - sum w) bg: the background enters like an alpha gradient.
          Ga[p] = static_cast<double>(g_alpha[row + i]);
        }
        // channel-outer: each read run is one contiguous row of a gradient plane
        for (int64_t c = 0; c < D; ++c) {
          const scalar_t* gr = g_out + c * HW + row;
          const double bc = static_cast<double>(bg[c]);
          double dbg = 0.0;
          for (int64_t i = 0; i < tv.w; ++i) {
            const int64_t p = j * kTile + i;
            const double gc = static_cast<double>(gr[i]);
            G[p * D + c] = gr[i];
            Ga[p] -= gc * bc;
            dbg += gc * (1.0 - static_cast<double>(alpha_out[row + i]));
          }
          d_bg[c] += dbg;
        }
      }
      for (int64_t k = begin + max_last - 1; k >= begin; --k) {
        const int64_t gi = ids[k];
        const int64_t rank = k - begin;
        const Rec& r = recs[gi];
        if (r.qlim < 0) continue;
        const scalar_t* v = vals + gi * D;
        double dmu = 0, dmv = 0, dA = 0, dB = 0, dC = 0, dop = 0;
        std::fill(dv.begin(), dv.end(), real(0));
        bool touched = false;
        const RowRange rr = row_range(g, tv, r);
        for (int64_t j = rr.j0; j < rr.j1; ++j) {
          const double dy = rr.dy0 + j;
          for (int ch = 0; ch < tv.w; ch += N) {
            if (chunk_outside(rr.dx0, ch, N, r.ru, g.wrap)) continue;
            row_alpha<real>(r.A, r.B, r.C, r.o, r.qlim, rr.dx0, dy, wrap, ch, &a, &gs);
            for (int64_t l = 0; l < N && ch + l < tv.w; ++l) {
              if (!(a[l] > 0)) continue;
              const int64_t i = ch + l;
              const int64_t p = j * kTile + i;
              if (rank >= last[p]) continue;
              double dx = rr.dx0 + i;
              if (g.wrap > 0 && dx >= 0.5 * g.wrap) dx -= g.wrap;
              const double gauss = static_cast<double>(gs[l]);
              const double al = static_cast<double>(a[l]);
              const bool clamped = !(static_cast<real>(r.o) * gs[l] < static_cast<real>(kAlphaMax));
              touched = true;
              const double one_m = 1.0 - al;
              T[p] /= one_m;  // transmittance in front of this Gaussian
              const double w = al * T[p];
              const scalar_t* gp = G.data() + p * D;
              scalar_t* sp = S.data() + p * D;
              double da = Ga[p] * (T[p] - Sa[p] / one_m);
              // Channel loop in the compute type (float for float32 inputs) so it vectorises.
              const real tp = static_cast<real>(T[p]), inv = static_cast<real>(1.0 / one_m);
              const real ws = static_cast<real>(w);
              real dsum = 0;
              real* dvp = dv.data();
#pragma omp simd reduction(+ : dsum)
              for (int64_t c = 0; c < D; ++c) {
                const real gc = static_cast<real>(gp[c]), vc = static_cast<real>(v[c]);
                dvp[c] += ws * gc;
                dsum += gc * (tp * vc - static_cast<real>(sp[c]) * inv);
                sp[c] = static_cast<scalar_t>(static_cast<real>(sp[c]) + ws * vc);
              }
              da += static_cast<double>(dsum);
              Sa[p] += w;
              if (clamped) continue;  // clamped alpha: no gradient to opacity or shape
              dop += da * gauss;
              const double dq = -0.5 * al * da;
              dA += dq * dx * dx;
              dB += dq * 2.0 * dx * dy;
              dC += dq * dy * dy;
              const double dqdx = 2.0 * (r.A * dx + r.B * dy), dqdy = 2.0 * (r.B * dx + r.C * dy);
              dmu -= dq * dqdx;
              dmv -= dq * dqdy;
            }
          }
        }
        if (!touched) continue;
        // One atomic add per (tile, Gaussian) rather than per pixel.
#pragma omp atomic
        d_mean[2 * gi] += static_cast<scalar_t>(dmu);
#pragma omp atomic
        d_mean[2 * gi + 1] += static_cast<scalar_t>(dmv);
#pragma omp atomic
        d_conic[3 * gi] += static_cast<scalar_t>(dA);
#pragma omp atomic
        d_conic[3 * gi + 1] += static_cast<scalar_t>(dB);
#pragma omp atomic
        d_conic[3 * gi + 2] += static_cast<scalar_t>(dC);
#pragma omp atomic
        d_opac[gi] += static_cast<scalar_t>(dop);
        for (int64_t c = 0; c < D; ++c) {
#pragma omp atomic
          d_vals[gi * D + c] += static_cast<scalar_t>(dv[c]);
        }
      }
    }
  });
}

// Records for M sorted screen Gaussians given as separate arrays (training path).
template <typename scalar_t>
std::vector<Rec> make_records(const scalar_t* mean, const scalar_t* radii, const scalar_t* conic,
                              const scalar_t* opac, int64_t M) {
  std::vector<Rec> recs(M);
  parallel_range(M, 4096, [&](int64_t b, int64_t e) {
    for (int64_t i = b; i < e; ++i) {
      const double o = opac[i];
      recs[i] = make_rec(mean[2 * i], mean[2 * i + 1], radii[2 * i], radii[2 * i + 1], conic[3 * i],
                         conic[3 * i + 1], conic[3 * i + 2], o);
    }
  });
  return recs;
}

// Tile column tx folded into [0, ntx), without an integer division in the usual cases (a
// panorama's box spills over the seam by less than a turn).
inline int64_t wrap_tile(int64_t tx, int64_t ntx) {
  if (tx >= 0 && tx < ntx) return tx;
  if (tx < 0 && tx >= -ntx) return tx + ntx;
  if (tx >= ntx && tx < 2 * ntx) return tx - ntx;
  return ((tx % ntx) + ntx) % ntx;
}

// Per-tile lists of Gaussian indices 0..M-1 (input order kept inside every tile: counting sort).
// u, v, ru, rv are read through get(i, &u, &v, &ru, &rv).
template <typename Get>
void bin_impl(int64_t M, const Grid& g, Get get, std::vector<int64_t>& off, std::vector<int64_t>& ids) {
  const int64_t n_tiles = g.ntx * g.nty;
  std::vector<int32_t> tx0(M), tx1(M), ty0(M), ty1(M);
  off.assign(n_tiles + 1, 0);
  const double tile = static_cast<double>(g.tile);
  for (int64_t i = 0; i < M; ++i) {
    double u, v, ru, rv;
    get(i, u, v, ru, rv);
    ty0[i] = (int32_t)std::clamp<double>(std::floor((v - rv) / tile), 0, g.nty - 1);
    ty1[i] = (int32_t)std::clamp<double>(std::floor((v + rv) / tile), 0, g.nty - 1);
    double a = std::floor((u - ru) / tile), b = std::floor((u + ru) / tile);
    if (g.wrap > 0) {
      if (b - a + 1 >= g.ntx) {
        a = 0;
        b = g.ntx - 1;
      }
    } else {
      a = std::clamp<double>(a, 0, g.ntx - 1);
      b = std::clamp<double>(b, 0, g.ntx - 1);
    }
    tx0[i] = (int32_t)a;
    tx1[i] = (int32_t)b;
    for (int64_t ty = ty0[i]; ty <= ty1[i]; ++ty)
      for (int64_t tx = tx0[i]; tx <= tx1[i]; ++tx) ++off[ty * g.ntx + wrap_tile(tx, g.ntx) + 1];
  }
  for (int64_t t = 0; t < n_tiles; ++t) off[t + 1] += off[t];
  ids.resize(off[n_tiles]);
  std::vector<int64_t> fill(off.begin(), off.end() - 1);
  for (int64_t i = 0; i < M; ++i)
    for (int64_t ty = ty0[i]; ty <= ty1[i]; ++ty)
      for (int64_t tx = tx0[i]; tx <= tx1[i]; ++tx) ids[fill[ty * g.ntx + wrap_tile(tx, g.ntx)]++] = i;
}

// Indices of the valid entries sorted by depth, stable (ties keep input order): LSD radix sort on
// the bit pattern of the (positive) depth in its own dtype, 8 bits per pass, constant digits skipped.
template <typename scalar_t>
std::vector<int64_t> sort_valid_by_depth(const scalar_t* depth, const bool* valid, int64_t N) {
  using key_t = std::conditional_t<sizeof(scalar_t) == 4, uint32_t, uint64_t>;
  std::vector<key_t> key, key2;
  std::vector<int64_t> idx, idx2;
  key.reserve(N);
  idx.reserve(N);
  for (int64_t i = 0; i < N; ++i) {
    if (!valid[i]) continue;
    scalar_t d = depth[i];
    if (!(d > 0)) d = 0;  // valid depths are > 0 (positive floats order like their bits); +0 first
    key_t k;
    std::memcpy(&k, &d, sizeof(k));
    key.push_back(k);
    idx.push_back(i);
  }
  const int64_t M = static_cast<int64_t>(key.size());
  key2.resize(M);
  idx2.resize(M);
  for (int shift = 0; shift < int(8 * sizeof(key_t)); shift += 8) {
    int64_t count[257] = {0};
    for (int64_t i = 0; i < M; ++i) ++count[((key[i] >> shift) & 0xFF) + 1];
    bool constant = false;
    for (int b = 1; b <= 256; ++b) constant = constant || count[b] == M;
    if (constant) continue;
    for (int b = 0; b < 256; ++b) count[b + 1] += count[b];
    for (int64_t i = 0; i < M; ++i) {
      const int64_t dst = count[(key[i] >> shift) & 0xFF]++;
      key2[dst] = key[i];
      idx2[dst] = idx[i];
    }
    key.swap(key2);
    idx.swap(idx2);
  }
  return idx;
}

// Fused inference-only projection (no autograd): the same math as project.py, in double, one
// Gaussian per iteration, OpenMP over Gaussians. Used when no input needs a gradient; project.py
// stays the differentiable ground truth and the tests compare the two.
constexpr double kPoleBlendCos = 0.1;  // project.py's POLE_BLEND_COS
constexpr double kFrustumMargin = 0.3;  // project.py's FRUSTUM_MARGIN

struct CamParams {
  bool equirect;
  double fx, fy, cx, cy;
  int64_t H, W;
  double near, far;  // far < 0: no far plane
};

// project.py's frustum_clamped: a pinhole camera-frame point's x/z and y/z clamped to the frustum
// widened by kFrustumMargin of its tangent on each side.
inline void frustum_clamped(const CamParams& cam, double x, double y, double z, double& xz, double& yz) {
  const double tx = 0.5 * cam.W / cam.fx, ty = 0.5 * cam.H / cam.fy;
  xz = std::clamp(x / z, -cam.cx / cam.fx - kFrustumMargin * tx, (cam.W - cam.cx) / cam.fx + kFrustumMargin * tx);
  yz = std::clamp(y / z, -cam.cy / cam.fy - kFrustumMargin * ty, (cam.H - cam.cy) / cam.fy + kFrustumMargin * ty);
}

template <typename scalar_t>
void project_impl(const scalar_t* means, const scalar_t* scales, const scalar_t* quats, const scalar_t* opac,
                  const bool* finite_mask, const double* c2w, const CamParams cam, int64_t N, scalar_t* out_uv,
                  scalar_t* out_conic, scalar_t* out_cov, scalar_t* out_depth, scalar_t* out_radii, bool* out_valid,
                  bool cull_early = false, const int64_t* block_of = nullptr, const bool* block_keep = nullptr) {
  // cull_early is the fused render's mode: it reads only the valid entries, so a culled Gaussian gets
  // out_valid = false and nothing else is written (placeholders are for project_forward's callers).
  // block_of / block_keep (fused mode only): a Gaussian whose spatial block cannot reach the image
  // (culling.py's FrustumBlocks) is dropped before its mean is even transformed.
  const double kPi = 3.14159265358979323846;
  const double R[3][3] = {{c2w[0], c2w[1], c2w[2]}, {c2w[4], c2w[5], c2w[6]}, {c2w[8], c2w[9], c2w[10]}};
  const double t[3] = {c2w[3], c2w[7], c2w[11]};
  parallel_range(N, 2048, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      if (block_keep != nullptr && !block_keep[block_of[i]]) {
        out_valid[i] = false;
        continue;
      }
      const double m[3] = {(double)means[3 * i] - t[0], (double)means[3 * i + 1] - t[1], (double)means[3 * i + 2] - t[2]};
      double p[3];
      for (int k = 0; k < 3; ++k) p[k] = m[0] * R[0][k] + m[1] * R[1][k] + m[2] * R[2][k];
      const double depth = cam.equirect ? std::sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]) : p[2];
      bool valid = std::isfinite(depth) && depth > 0 && depth >= cam.near && (cam.far < 0 || depth <= cam.far) &&
                   (finite_mask == nullptr || finite_mask[i]) && (double)opac[i] >= kAlphaMin;
      double u = 0, v = 0, a = 1, b = 0, c = 1;
      if (valid && cull_early && !cam.equirect) {
        // A bound on the footprint before the covariance (most of a pinhole's Gaussians are out of
        // view): the 2D covariance's largest eigenvalue is at most its trace, <= |J|_F^2 s_max^2
        // + 0.6, so a box of that radius that misses the image means the exact one misses it too
        // (same `valid`; only the skipped entries' conic / radii outputs stay at their defaults).
        const double z = p[2];
        double xz, yz;
        frustum_clamped(cam, p[0], p[1], z, xz, yz);
        const double smax = std::max({std::abs((double)scales[3 * i]), std::abs((double)scales[3 * i + 1]),
                                      std::abs((double)scales[3 * i + 2])});
        const double jf2 = (cam.fx * cam.fx * (1 + xz * xz) + cam.fy * cam.fy * (1 + yz * yz)) / (z * z);
        const double rb = 3.5 * std::sqrt(jf2 * smax * smax + 0.6) + 1.0;
        const double uu = cam.fx * p[0] / z + cam.cx, vv = cam.fy * p[1] / z + cam.cy;
        if (uu + rb <= 0 || uu - rb >= cam.W || vv + rb <= 0 || vv - rb >= cam.H) valid = false;
      }
      if (cull_early && !valid) {
        out_valid[i] = false;
        continue;
      }
      if (valid) {
        double J[2][3];
        const double x = p[0], y = p[1], z = p[2];
        if (cam.equirect) {
          const double rho2 = x * x + z * z;
          const bool pole = rho2 <= 1e-18 * (rho2 + y * y);  // cos(lat) <= 1e-9: project.py's _POLE_COS
          const double lon = pole ? 0.0 : std::atan2(x, z);
          const double rho = pole ? 0.0 : std::sqrt(rho2);
          const double lat = std::atan2(-y, rho);
          const double r = std::sqrt(rho2 + y * y);
          const double su = cam.W / (2.0 * kPi), sv = -cam.H / kPi;
          const double cl = std::cos(lat), sl = std::sin(lat), co = std::cos(lon), so = std::sin(lon);
          const double fu = su / (r * std::max(cl, 1e-9)), fv = sv / r;
          J[0][0] = co * fu; J[0][1] = 0.0; J[0][2] = -so * fu;
          J[1][0] = -sl * so * fv; J[1][1] = -cl * fv; J[1][2] = -sl * co * fv;
          const double uu = (lon + kPi) * su;
          u = uu - cam.W * std::floor(uu / cam.W);
          v = (0.5 * kPi - lat) * (cam.H / kPi);
        } else {
          // The Jacobian at x/z, y/z clamped to the widened frustum.
          double xz, yz;
          frustum_clamped(cam, x, y, z, xz, yz);
          J[0][0] = cam.fx / z; J[0][1] = 0.0; J[0][2] = -cam.fx * (xz * z) / (z * z);
          J[1][0] = 0.0; J[1][1] = cam.fy / z; J[1][2] = -cam.fy * (yz * z) / (z * z);
          u = cam.fx * x / z + cam.cx;
          v = cam.fy * y / z + cam.cy;
        }
        // rotation of the Gaussian from its (normalised) quaternion, times diag(s)
        double qw = quats[4 * i], qx = quats[4 * i + 1], qy = quats[4 * i + 2], qz = quats[4 * i + 3];
        const double qn = std::max(std::sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12);
        qw /= qn; qx /= qn; qy /= qn; qz /= qn;
        const double G[3][3] = {
            {1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)},
            {2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)},
            {2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)}};
        const double s[3] = {scales[3 * i], scales[3 * i + 1], scales[3 * i + 2]};
        double K[2][3], L[2][3];
        for (int r = 0; r < 2; ++r)
          for (int k = 0; k < 3; ++k) K[r][k] = J[r][0] * R[k][0] + J[r][1] * R[k][1] + J[r][2] * R[k][2];
        for (int r = 0; r < 2; ++r)
          for (int k = 0; k < 3; ++k) L[r][k] = (K[r][0] * G[0][k] + K[r][1] * G[1][k] + K[r][2] * G[2][k]) * s[k];
        a = L[0][0] * L[0][0] + L[0][1] * L[0][1] + L[0][2] * L[0][2] + 0.3;
        b = L[0][0] * L[1][0] + L[0][1] * L[1][1] + L[0][2] * L[1][2];
        c = L[1][0] * L[1][0] + L[1][1] * L[1][1] + L[1][2] * L[1][2];
        const double r2 = x * x + y * y + z * z, cos2 = (x * x + z * z) / r2;
        if (cam.equirect && cos2 < kPoleBlendCos * kPoleBlendCos) {
          // project.py's _pole_blend (only inside the cap, where its weight is below 1): (b, c)
          // towards their longitude average.
          double S[3] = {0, 0, 0};  // diagonal of the camera-frame covariance (R^T G diag(s))(...)^T
          for (int i3 = 0; i3 < 3; ++i3)
            for (int k = 0; k < 3; ++k) {
              const double mk = (R[0][i3] * G[0][k] + R[1][i3] * G[1][k] + R[2][i3] * G[2][k]) * s[k];
              S[i3] += mk * mk;
            }
          const double tb = cos2 / (kPoleBlendCos * kPoleBlendCos);
          const double c_avg = (cam.H / kPi) * (cam.H / kPi) / r2 * ((1.0 - cos2) * 0.5 * (S[0] + S[2]) + cos2 * S[1]);
          b *= tb;
          c = c_avg + tb * (c - c_avg);
        }
        c += 0.3;
        const double det = a * c - b * b;
        valid = std::isfinite(a) && std::isfinite(b) && std::isfinite(c) && det > 0;
        if (!valid) { a = 1; b = 0; c = 1; }
      }
      const double det = a * c - b * b;
      const double ru = cam.equirect ? std::min(3.5 * std::sqrt(a), (double)cam.W) : 3.5 * std::sqrt(a);
      const double rv = 3.5 * std::sqrt(c);
      if (valid) {
        bool on = (v + rv > 0) && (v - rv < cam.H) && std::isfinite(u) && std::isfinite(v);
        if (!cam.equirect) on = on && (u + ru > 0) && (u - ru < cam.W);
        valid = on;
      }
      out_uv[2 * i] = valid ? u : 0; out_uv[2 * i + 1] = valid ? v : 0;
      out_conic[3 * i] = c / det; out_conic[3 * i + 1] = -b / det; out_conic[3 * i + 2] = a / det;
      out_cov[3 * i] = a; out_cov[3 * i + 1] = b; out_cov[3 * i + 2] = c;
      out_depth[i] = valid ? depth : 0;
      out_radii[2 * i] = ru; out_radii[2 * i + 1] = rv;
      out_valid[i] = valid;
    }
  });
}

Grid make_grid(int64_t H, int64_t W, int64_t tile, double wrap) {
  TORCH_CHECK(H > 0 && W > 0 && tile > 0, "splat_cpu: bad image/tile size");
  return Grid{H, W, tile, (W + tile - 1) / tile, (H + tile - 1) / tile, wrap};
}

}  // namespace

// Per-tile Gaussian lists (input order = depth order is kept inside every tile).
std::vector<torch::Tensor> bin_gaussians(torch::Tensor means2d, torch::Tensor radii, int64_t H, int64_t W,
                                         double wrap, int64_t tile) {
  const Grid g = make_grid(H, W, tile, wrap);
  auto m = means2d.to(torch::kFloat64).contiguous();
  auto r = radii.to(torch::kFloat64).contiguous();
  const double* mp = m.data_ptr<double>();
  const double* rp = r.data_ptr<double>();
  std::vector<int64_t> off, ids;
  bin_impl(m.size(0), g,
           [&](int64_t i, double& u, double& v, double& ru, double& rv) {
             u = mp[2 * i];
             v = mp[2 * i + 1];
             ru = rp[2 * i];
             rv = rp[2 * i + 1];
           },
           off, ids);
  auto offsets = torch::from_blob(off.data(), {(int64_t)off.size()}, torch::kInt64).clone();
  auto id_t = torch::from_blob(ids.data(), {(int64_t)ids.size()}, torch::kInt64).clone();
  return {offsets, id_t};
}

std::vector<torch::Tensor> rasterize_forward(torch::Tensor means2d, torch::Tensor radii, torch::Tensor conics,
                                             torch::Tensor opac, torch::Tensor vals, torch::Tensor bg,
                                             torch::Tensor offsets, torch::Tensor ids, int64_t H, int64_t W,
                                             double wrap, int64_t tile, double t_min) {
  TORCH_CHECK(t_min > 0 && t_min < 1, "splat_cpu: t_min must lie in (0, 1), got ", t_min);
  TORCH_CHECK(tile == kTile, "splat_cpu: the kernel's tile edge is ", kTile, ", got ", tile);
  const Grid g = make_grid(H, W, tile, wrap);
  const int64_t D = vals.size(1);
  auto opts = vals.options();
  auto out = torch::empty({D, H, W}, opts);
  auto alpha = torch::empty({1, H, W}, opts);
  auto t_final = torch::empty({H, W}, opts.dtype(torch::kFloat64));
  auto n_contrib = torch::empty({H, W}, opts.dtype(torch::kInt64));
  AT_DISPATCH_FLOATING_TYPES(vals.scalar_type(), "splat_cpu_forward", [&] {
    const auto recs = make_records<scalar_t>(means2d.data_ptr<scalar_t>(), radii.data_ptr<scalar_t>(),
                                             conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                                             means2d.size(0));
    forward_impl<scalar_t>(recs.data(), vals.data_ptr<scalar_t>(), bg.data_ptr<scalar_t>(), D,
                           offsets.data_ptr<int64_t>(), ids.data_ptr<int64_t>(), g, t_min, out.data_ptr<scalar_t>(),
                           alpha.data_ptr<scalar_t>(), t_final.data_ptr<double>(), n_contrib.data_ptr<int64_t>());
  });
  return {out, alpha, t_final, n_contrib};
}

std::vector<torch::Tensor> rasterize_backward(torch::Tensor means2d, torch::Tensor radii, torch::Tensor conics,
                                              torch::Tensor opac, torch::Tensor vals, torch::Tensor bg,
                                              torch::Tensor offsets, torch::Tensor ids, int64_t H, int64_t W,
                                              double wrap, int64_t tile, torch::Tensor alpha,
                                              torch::Tensor t_final, torch::Tensor n_contrib, torch::Tensor g_out,
                                              torch::Tensor g_alpha) {
  TORCH_CHECK(tile == kTile, "splat_cpu: the kernel's tile edge is ", kTile, ", got ", tile);
  const Grid g = make_grid(H, W, tile, wrap);
  const int64_t D = vals.size(1);
  auto d_mean = torch::zeros_like(means2d);
  auto d_conic = torch::zeros_like(conics);
  auto d_opac = torch::zeros_like(opac);
  auto d_vals = torch::zeros_like(vals);
  const int64_t nthreads = at::get_num_threads();
  auto d_bg_threads = torch::zeros({nthreads, D}, vals.options().dtype(torch::kFloat64));
  AT_DISPATCH_FLOATING_TYPES(vals.scalar_type(), "splat_cpu_backward", [&] {
    const auto recs = make_records<scalar_t>(means2d.data_ptr<scalar_t>(), radii.data_ptr<scalar_t>(),
                                             conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                                             means2d.size(0));
    backward_impl<scalar_t>(recs.data(), vals.data_ptr<scalar_t>(), bg.data_ptr<scalar_t>(), D,
                            offsets.data_ptr<int64_t>(), ids.data_ptr<int64_t>(), g, alpha.data_ptr<scalar_t>(),
                            t_final.data_ptr<double>(), n_contrib.data_ptr<int64_t>(), g_out.data_ptr<scalar_t>(),
                            g_alpha.data_ptr<scalar_t>(), d_mean.data_ptr<scalar_t>(), d_conic.data_ptr<scalar_t>(),
                            d_opac.data_ptr<scalar_t>(), d_vals.data_ptr<scalar_t>(), d_bg_threads.data_ptr<double>());
  });
  auto d_bg = d_bg_threads.sum(0).to(vals.scalar_type());
  return {d_mean, d_conic, d_opac, d_vals, d_bg};
}

// Valid indices (int64) sorted front to back by depth, ties by index (the training path's order).
torch::Tensor sort_valid(torch::Tensor depth, torch::Tensor valid) {
  auto d = depth.contiguous();
  auto v = valid.to(torch::kBool).contiguous();
  torch::Tensor res;
  AT_DISPATCH_FLOATING_TYPES(d.scalar_type(), "splat_cpu_sort", [&] {
    auto idx = sort_valid_by_depth<scalar_t>(d.data_ptr<scalar_t>(), v.data_ptr<bool>(), d.size(0));
    res = torch::from_blob(idx.data(), {(int64_t)idx.size()}, torch::kInt64).clone();
  });
  return res;
}
std::vector<torch::Tensor> project_forward_impl(torch::Tensor means, torch::Tensor scales, torch::Tensor quats,
                                                torch::Tensor opac, torch::Tensor finite_mask, torch::Tensor c2w,
                                                bool equirect, double fx, double fy, double cx, double cy, int64_t H,
                                                int64_t W, double near, double far, bool cull_early,
                                                torch::Tensor block_of = {}, torch::Tensor block_keep = {}) {
  const int64_t N = means.size(0);
  auto opts = means.options();
  auto uv = torch::empty({N, 2}, opts), conic = torch::empty({N, 3}, opts), cov = torch::empty({N, 3}, opts);
  auto depth = torch::empty({N}, opts), radii = torch::empty({N, 2}, opts);
  auto valid = torch::empty({N}, opts.dtype(torch::kBool));
  auto pose = c2w.to(torch::kFloat64).contiguous();
  const CamParams cam{equirect, fx, fy, cx, cy, H, W, near, far};
  const bool* mask = finite_mask.numel() ? finite_mask.data_ptr<bool>() : nullptr;
  const bool blocks = block_keep.defined() && block_keep.numel() > 0;
  if (blocks) {
    TORCH_CHECK(cull_early, "splat_cpu: block culling is for the fused render only");
    TORCH_CHECK(block_of.scalar_type() == torch::kInt64 && block_of.numel() == N && block_of.is_contiguous(),
                "splat_cpu: block_of must be a contiguous int64 tensor with one entry per Gaussian");
    TORCH_CHECK(block_keep.scalar_type() == torch::kBool && block_keep.is_contiguous(),
                "splat_cpu: block_keep must be a contiguous bool tensor");
    // Every block id must index block_keep: checked here once (one pass), not per Gaussian in the loop.
    if (N > 0) {
      const auto [lo, hi] = torch::aminmax(block_of);
      TORCH_CHECK(lo.item<int64_t>() >= 0 && hi.item<int64_t>() < block_keep.numel(),
                  "splat_cpu: block_of holds an id outside block_keep");
    }
  }
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "splat_cpu_project", [&] {
    project_impl<scalar_t>(means.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                           opac.data_ptr<scalar_t>(), mask, pose.data_ptr<double>(), cam, N,
                           uv.data_ptr<scalar_t>(), conic.data_ptr<scalar_t>(), cov.data_ptr<scalar_t>(),
                           depth.data_ptr<scalar_t>(), radii.data_ptr<scalar_t>(), valid.data_ptr<bool>(),
                           cull_early, blocks ? block_of.data_ptr<int64_t>() : nullptr,
                           blocks ? block_keep.data_ptr<bool>() : nullptr);
  });
  return {uv, conic, cov, depth, radii, valid};
}


// Every Gaussian's projection (the Python-facing entry; the fused render culls early instead).
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor scales, torch::Tensor quats,
                                           torch::Tensor opac, torch::Tensor finite_mask, torch::Tensor c2w,
                                           bool equirect, double fx, double fy, double cx, double cy, int64_t H,
                                           int64_t W, double near, double far) {
  return project_forward_impl(means, scales, quats, opac, finite_mask, c2w, equirect, fx, fy, cx, cy, H, W, near,
                              far, false);
}

// Fused inference path for one camera: project, cull, depth-sort, bin, pack, rasterise.
// values per Gaussian = (colour (3), depth (1), features (C)); bg has 4 + C entries.
std::vector<torch::Tensor> render_forward(torch::Tensor means, torch::Tensor scales, torch::Tensor quats,
                                          torch::Tensor opac, torch::Tensor colors, torch::Tensor feats,
                                          torch::Tensor finite_mask, torch::Tensor c2w, bool equirect, double fx,
                                          double fy, double cx, double cy, int64_t H, int64_t W, double near,
                                          double far, torch::Tensor bg, double t_min, torch::Tensor block_of,
                                          torch::Tensor block_keep) {
  TORCH_CHECK(t_min > 0 && t_min < 1, "splat_cpu: t_min must lie in (0, 1), got ", t_min);
  auto proj = project_forward_impl(means, scales, quats, opac, finite_mask, c2w, equirect, fx, fy, cx, cy, H,
                                   W, near, far, /*cull_early=*/true, block_of, block_keep);
  const auto& uv = proj[0];
  const auto& conic = proj[1];
  const auto& depth = proj[3];
  const auto& radii = proj[4];
  const auto& valid = proj[5];
  const Grid g = make_grid(H, W, kTile, equirect ? double(W) : 0.0);
  auto col = colors.contiguous();
  auto fea = feats.contiguous();
  const int64_t C = fea.size(1), D = 4 + C;
  auto opts = means.options();
  auto out = torch::empty({D, H, W}, opts);
  auto alpha = torch::empty({1, H, W}, opts);
  auto bgc = bg.contiguous();
  TORCH_CHECK(bgc.numel() == D, "splat_cpu: background needs ", D, " entries");
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "splat_cpu_render", [&] {
    const scalar_t* dp = depth.data_ptr<scalar_t>();
    const auto order = sort_valid_by_depth<scalar_t>(dp, valid.data_ptr<bool>(), depth.size(0));
    const int64_t M = static_cast<int64_t>(order.size());
    std::vector<Rec> recs(M);
    std::vector<scalar_t> vals(M * D);
    const scalar_t* up = uv.data_ptr<scalar_t>();
    const scalar_t* cp = conic.data_ptr<scalar_t>();
    const scalar_t* rp = radii.data_ptr<scalar_t>();
    const scalar_t* op = opac.data_ptr<scalar_t>();
    const scalar_t* colp = col.data_ptr<scalar_t>();
    const scalar_t* fp = fea.data_ptr<scalar_t>();
    parallel_range(M, 4096, [&](int64_t b, int64_t e) {
      for (int64_t k = b; k < e; ++k) {
        const int64_t i = order[k];
        const double o = op[i];
        recs[k] = make_rec(up[2 * i], up[2 * i + 1], rp[2 * i], rp[2 * i + 1], cp[3 * i], cp[3 * i + 1],
                           cp[3 * i + 2], o);
        scalar_t* v = vals.data() + k * D;
        v[0] = colp[3 * i];
        v[1] = colp[3 * i + 1];
        v[2] = colp[3 * i + 2];
        v[3] = dp[i];
        for (int64_t c = 0; c < C; ++c) v[4 + c] = fp[i * C + c];
      }
    });
    std::vector<int64_t> off, ids;
    bin_impl(M, g,
             [&](int64_t k, double& u, double& v, double& ru, double& rv) {
               u = recs[k].mu;
               v = recs[k].mv;
               ru = recs[k].ru;
               rv = recs[k].rv;
             },
             off, ids);
    forward_impl<scalar_t>(recs.data(), vals.data(), bgc.data_ptr<scalar_t>(), D, off.data(), ids.data(), g,
                           t_min, out.data_ptr<scalar_t>(), alpha.data_ptr<scalar_t>(), nullptr, nullptr);
  });
  return {out, alpha};
}

// views_cpu.cpp (the same extension): best-view selection of gaussians/views.py.
torch::Tensor best_view_mask_cpu(torch::Tensor probes, torch::Tensor own_iv, torch::Tensor facing, int64_t own,
                                 std::vector<torch::Tensor> w2c, torch::Tensor cameras,
                                 std::vector<torch::Tensor> depth, std::vector<torch::Tensor> interval,
                                 std::vector<torch::Tensor> normals, std::vector<torch::Tensor> free,
                                 torch::Tensor centres, torch::Tensor min_angle, torch::Tensor carve, double tol,
                                 double step, double owner_cos, int64_t threads);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("project_forward", &project_forward, "fused inference-only projection");
  m.def("render_forward", &render_forward, "fused inference-only projection + sort + bin + rasterise");
  m.def("sort_valid", &sort_valid, "valid indices sorted by depth (stable)");
  m.def("bin_gaussians", &bin_gaussians, "per-tile depth-ordered Gaussian lists");
  m.def("rasterize_forward", &rasterize_forward, "tile-parallel forward rasterisation");
  m.def("rasterize_backward", &rasterize_backward, "tile-parallel backward rasterisation");
  // Releases the GIL: build_scene selects several frames' Gaussians at once on Python threads.
  m.def("best_view_mask", &best_view_mask_cpu, "best-view selection of one frame's Gaussians",
        py::call_guard<py::gil_scoped_release>());
}
