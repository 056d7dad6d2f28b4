// Tile-parallel CPU rasteriser for depth-sorted screen Gaussians (forward and backward).
//
// Contract identical to backends/reference.py: per pixel, front to back over the tile's list,
// q = d^T conic d, skip q > 3.5^2, alpha = min(0.99, o exp(-q/2)), skip alpha < 1/255,
// w = alpha T, stop after the Gaussian that drops T below 1e-4. Outputs
// image[k] = sum w v_k + (1 - sum w) bg_k and alpha = sum w.
// Loops run Gaussian-outer / pixel-inner inside a tile (parameters are loaded once per tile and
// the pixel loop is branch-light); transmittance and sums are accumulated in double.
#include <torch/extension.h>
#include <ATen/Parallel.h>
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <vector>

namespace {

constexpr double kCutoff2 = 3.5 * 3.5;
constexpr double kAlphaMax = 0.99;
constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kTMin = 1e-4;

struct Grid {
  int64_t H, W, tile, ntx, nty;
  double wrap;  // 0 = no horizontal wrap
};

inline double wrap_dx(double dx, double wrap) {
  if (wrap <= 0) return dx;
  return dx - wrap * std::floor((dx + 0.5 * wrap) / wrap);
}

template <typename T>
struct TileView {
  // Pixel coordinates of a tile and the number of real (in-image) pixels.
  int64_t x0, y0, w, h;
};

inline TileView<double> tile_view(const Grid& g, int64_t t) {
  TileView<double> v;
  v.x0 = (t % g.ntx) * g.tile;
  v.y0 = (t / g.ntx) * g.tile;
  v.w = std::min(g.tile, g.W - v.x0);
  v.h = std::min(g.tile, g.H - v.y0);
  return v;
}


// Pixel window of one Gaussian's footprint box inside one tile: local columns [i0, i1), rows
// [j0, j1) and the offsets (pixel centre - mean) of local pixel (0, 0). Offsets inside the
// window never cross the panorama seam because the box half-width is < W/2 - tile there.
struct Window {
  int64_t i0, i1, j0, j1;
  double dx0, dy0;
};

inline Window window(const Grid& g, const TileView<double>& tv, double mu, double mv, double ru, double rv) {
  Window w;
  w.dy0 = tv.y0 + 0.5 - mv;
  w.j0 = std::max<int64_t>(0, (int64_t)std::ceil(-rv - w.dy0));
  w.j1 = std::min<int64_t>(tv.h, (int64_t)std::floor(rv - w.dy0) + 1);
  const double raw = tv.x0 + 0.5 - mu;
  w.dx0 = wrap_dx(raw, g.wrap);
  if (g.wrap > 0 && 2.0 * ru >= g.wrap - 2.0 * g.tile) {
    // Near-full-width footprint: per-pixel wrapping, every column.
    w.i0 = 0;
    w.i1 = tv.w;
    w.dx0 = std::nan("");
    return w;
  }
  w.i0 = std::max<int64_t>(0, (int64_t)std::ceil(-ru - w.dx0));
  w.i1 = std::min<int64_t>(tv.w, (int64_t)std::floor(ru - w.dx0) + 1);
  return w;
}

inline double window_dx(const Grid& g, const TileView<double>& tv, const Window& w, double mu, int64_t i) {
  if (std::isnan(w.dx0)) return wrap_dx(tv.x0 + i + 0.5 - mu, g.wrap);
  return w.dx0 + i;
}


// Columns [i_lo, i_hi) of row offset dy whose pixels can satisfy q <= qlim: the chord of the
// ellipse A dx^2 + 2 B dx dy + C dy^2 = qlim (A > 0), widened by a hair (the exact test follows).
inline bool row_span(const Window& w, double A, double B, double C, double qlim, double dy, int64_t& i_lo,
                     int64_t& i_hi) {
  i_lo = w.i0;
  i_hi = w.i1;
  if (std::isnan(w.dx0)) return true;  // per-pixel wrapping: test every column
  const double disc = B * B * dy * dy - A * (C * dy * dy - qlim);
  if (disc < 0) return false;
  const double sq = std::sqrt(disc), lo = (-B * dy - sq) / A, hi = (-B * dy + sq) / A;
  const double pad = 1e-7 * (1.0 + std::abs(lo) + std::abs(hi));
  i_lo = std::max<int64_t>(w.i0, (int64_t)std::ceil(lo - pad - w.dx0));
  i_hi = std::min<int64_t>(w.i1, (int64_t)std::floor(hi + pad - w.dx0) + 1);
  return i_lo < i_hi;
}

// Largest q at which alpha = o exp(-q/2) can still reach 1/255 (tiny margin: exact test follows).
inline double q_limit(double o) {
  if (!(o >= kAlphaMin)) return -1.0;
  return std::min(kCutoff2, 2.0 * std::log(o / kAlphaMin) + 1e-6);
}

template <typename scalar_t>
void forward_impl(const scalar_t* mean, const scalar_t* radii, const scalar_t* conic, const scalar_t* opac, const scalar_t* vals,
                  const scalar_t* bg, int64_t D, const int64_t* offs, const int64_t* ids, const Grid& g,
                  scalar_t* out, scalar_t* alpha_out, double* t_final, int64_t* n_contrib) {
  const int64_t n_tiles = g.ntx * g.nty;
  const int64_t HW = g.H * g.W;
#pragma omp parallel num_threads(at::get_num_threads())
  {
    const int64_t P = g.tile * g.tile;
    // Channel sums in scalar_t keep a float tile (256 x D) in L1; transmittance stays double.
    std::vector<double> T(P), asum(P);
    std::vector<scalar_t> acc(P * D);
    std::vector<int64_t> last(P);
    std::vector<char> done(P);
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      const auto tv = tile_view(g, t);
      const int64_t np = tv.w * tv.h;
      std::fill(T.begin(), T.begin() + np, 1.0);
      std::fill(acc.begin(), acc.begin() + np * D, scalar_t(0));
      std::fill(asum.begin(), asum.begin() + np, 0.0);
      std::fill(last.begin(), last.begin() + np, 0);
      std::fill(done.begin(), done.begin() + np, 0);
      int64_t n_done = 0;
      const int64_t begin = offs[t], end = offs[t + 1];
      for (int64_t k = begin; k < end && n_done < np; ++k) {
        const int64_t gi = ids[k];
        const double mu = mean[2 * gi], mv = mean[2 * gi + 1];
        const double A = conic[3 * gi], B = conic[3 * gi + 1], C = conic[3 * gi + 2];
        const double o = opac[gi];
        const scalar_t* v = vals + gi * D;
        const double qlim = q_limit(o);
        if (qlim < 0) continue;
        const Window win = window(g, tv, mu, mv, radii[2 * gi], radii[2 * gi + 1]);
        for (int64_t j = win.j0; j < win.j1; ++j) {
          const double dy = win.dy0 + j;
          int64_t i_lo, i_hi;
          if (!row_span(win, A, B, C, qlim, dy, i_lo, i_hi)) continue;
          for (int64_t i = i_lo; i < i_hi; ++i) {
            const int64_t p = j * tv.w + i;
            if (done[p]) continue;
            const double dx = window_dx(g, tv, win, mu, i);
            const double q = A * dx * dx + 2.0 * B * dx * dy + C * dy * dy;
            if (!(q <= qlim)) continue;
            const double a = std::min(kAlphaMax, o * std::exp(-0.5 * q));
            if (a < kAlphaMin) continue;
            const double w = a * T[p];
            const scalar_t ws = static_cast<scalar_t>(w);
            scalar_t* ap = acc.data() + p * D;
            for (int64_t c = 0; c < D; ++c) ap[c] += ws * v[c];
            asum[p] += w;
            T[p] *= (1.0 - a);
            last[p] = k - begin + 1;
            if (T[p] < kTMin) {
              done[p] = 1;
              ++n_done;
            }
          }
        }
      }
      for (int64_t p = 0; p < np; ++p) {
        const int64_t pix = (tv.y0 + p / tv.w) * g.W + tv.x0 + (p % tv.w);
        const double rest = 1.0 - asum[p];
        for (int64_t c = 0; c < D; ++c) out[c * HW + pix] = static_cast<scalar_t>(acc[p * D + c] + rest * bg[c]);
        alpha_out[pix] = static_cast<scalar_t>(asum[p]);
        t_final[pix] = T[p];
        n_contrib[pix] = last[p];
      }
    }
  }
}

template <typename scalar_t>
void backward_impl(const scalar_t* mean, const scalar_t* radii, const scalar_t* conic, const scalar_t* opac, const scalar_t* vals,
                   const scalar_t* bg, int64_t D, const int64_t* offs, const int64_t* ids, const Grid& g,
                   const scalar_t* alpha_out, const double* t_final, const int64_t* n_contrib,
                   const scalar_t* g_out, const scalar_t* g_alpha, scalar_t* d_mean, scalar_t* d_conic,
                   scalar_t* d_opac, scalar_t* d_vals, double* d_bg_threads) {
  const int64_t n_tiles = g.ntx * g.nty;
  const int64_t HW = g.H * g.W;
#pragma omp parallel num_threads(at::get_num_threads())
  {
    const int64_t P = g.tile * g.tile;
    std::vector<double> T(P), Sa(P), Ga(P), dv(D);
    std::vector<scalar_t> S(P * D), G(P * D);
    std::vector<int64_t> last(P);
    double* d_bg = d_bg_threads + omp_get_thread_num() * D;
#pragma omp for schedule(dynamic, 1)
    for (int64_t t = 0; t < n_tiles; ++t) {
      const auto tv = tile_view(g, t);
      const int64_t np = tv.w * tv.h;
      const int64_t begin = offs[t];
      int64_t max_last = 0;
      for (int64_t p = 0; p < np; ++p) {
        const int64_t pix = (tv.y0 + p / tv.w) * g.W + tv.x0 + (p % tv.w);
        T[p] = t_final[pix];
        last[p] = n_contrib[pix];
        max_last = std::max(max_last, last[p]);
        Sa[p] = 0.0;
        double gbg = 0.0;
        for (int64_t c = 0; c < D; ++c) {
          const double gc = g_out[c * HW + pix];
          G[p * D + c] = static_cast<scalar_t>(gc);
          S[p * D + c] = scalar_t(0);
          gbg += gc * bg[c];
          d_bg[c] += gc * (1.0 - static_cast<double>(alpha_out[pix]));
        }
        // image = sum w v + (1 - sum w) bg: the background enters like an alpha gradient.
        Ga[p] = static_cast<double>(g_alpha[pix]) - gbg;
      }
      for (int64_t k = begin + max_last - 1; k >= begin; --k) {
        const int64_t gi = ids[k];
        const int64_t rank = k - begin;
        const double mu = mean[2 * gi], mv = mean[2 * gi + 1];
        const double A = conic[3 * gi], B = conic[3 * gi + 1], C = conic[3 * gi + 2];
        const double o = opac[gi];
        const scalar_t* v = vals + gi * D;
        double dmu = 0, dmv = 0, dA = 0, dB = 0, dC = 0, dop = 0;
        std::fill(dv.begin(), dv.end(), 0.0);
        bool touched = false;
        const double qlim = q_limit(o);
        if (qlim < 0) continue;
        const Window win = window(g, tv, mu, mv, radii[2 * gi], radii[2 * gi + 1]);
        for (int64_t j = win.j0; j < win.j1; ++j) {
        const double dy = win.dy0 + j;
        int64_t i_lo, i_hi;
        if (!row_span(win, A, B, C, qlim, dy, i_lo, i_hi)) continue;
        for (int64_t i = i_lo; i < i_hi; ++i) {
          const int64_t p = j * tv.w + i;
          if (rank >= last[p]) continue;
          const double dx = window_dx(g, tv, win, mu, i);
          const double q = A * dx * dx + 2.0 * B * dx * dy + C * dy * dy;
          if (!(q <= qlim)) continue;
          const double gauss = std::exp(-0.5 * q);
          const double raw = o * gauss;
          const double a = std::min(kAlphaMax, raw);
          if (a < kAlphaMin) continue;
          touched = true;
          const double one_m = 1.0 - a;
          T[p] /= one_m;  // transmittance in front of this Gaussian
          const double w = a * T[p];
          const scalar_t* gp = G.data() + p * D;
          scalar_t* sp = S.data() + p * D;
          double da = Ga[p] * (T[p] - Sa[p] / one_m);
          const double tp = T[p], inv = 1.0 / one_m;
          const scalar_t ws = static_cast<scalar_t>(w);
          double dsum = 0.0;
          for (int64_t c = 0; c < D; ++c) {
            dv[c] += w * gp[c];
            dsum += gp[c] * (tp * v[c] - sp[c] * inv);
            sp[c] += ws * v[c];
          }
          da += dsum;
          Sa[p] += w;
          if (raw > kAlphaMax) continue;  // clamped alpha: no gradient to opacity or shape
          dop += da * gauss;
          const double dq = -0.5 * a * da;
          dA += dq * dx * dx;
          dB += dq * 2.0 * dx * dy;
          dC += dq * dy * dy;
          const double dqdx = 2.0 * (A * dx + B * dy), dqdy = 2.0 * (B * dx + C * dy);
          dmu -= dq * dqdx;
          dmv -= dq * dqdy;
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
  }
}


// Fused inference-only projection (no autograd): the same math as project.py, in double, one
// Gaussian per iteration, OpenMP over Gaussians. Used when no input needs a gradient; project.py
// stays the differentiable ground truth and the tests compare the two.
struct CamParams {
  bool equirect;
  double fx, fy, cx, cy;
  int64_t H, W;
  double near, far;  // far < 0: no far plane
};

template <typename scalar_t>
void project_impl(const scalar_t* means, const scalar_t* scales, const scalar_t* quats, const scalar_t* opac,
                  const bool* finite_mask, const double* c2w, const CamParams cam, int64_t N, scalar_t* out_uv,
                  scalar_t* out_conic, scalar_t* out_cov, scalar_t* out_depth, scalar_t* out_radii, bool* out_valid) {
  const double kPi = 3.14159265358979323846;
  const double R[3][3] = {{c2w[0], c2w[1], c2w[2]}, {c2w[4], c2w[5], c2w[6]}, {c2w[8], c2w[9], c2w[10]}};
  const double t[3] = {c2w[3], c2w[7], c2w[11]};
  at::parallel_for(0, N, 2048, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      const double m[3] = {(double)means[3 * i] - t[0], (double)means[3 * i + 1] - t[1], (double)means[3 * i + 2] - t[2]};
      double p[3];
      for (int k = 0; k < 3; ++k) p[k] = m[0] * R[0][k] + m[1] * R[1][k] + m[2] * R[2][k];
      const double depth = cam.equirect ? std::sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]) : p[2];
      bool valid = std::isfinite(depth) && depth > 0 && depth >= cam.near && (cam.far < 0 || depth <= cam.far) &&
                   (finite_mask == nullptr || finite_mask[i]) && (double)opac[i] >= kAlphaMin;
      double u = 0, v = 0, a = 1, b = 0, c = 1;
      if (valid) {
        double J[2][3];
        const double x = p[0], y = p[1], z = p[2];
        if (cam.equirect) {
          const double rho2 = x * x + z * z;
          const bool pole = rho2 < 1e-60;
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
          J[0][0] = cam.fx / z; J[0][1] = 0.0; J[0][2] = -cam.fx * x / (z * z);
          J[1][0] = 0.0; J[1][1] = cam.fy / z; J[1][2] = -cam.fy * y / (z * z);
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
        c = L[1][0] * L[1][0] + L[1][1] * L[1][1] + L[1][2] * L[1][2] + 0.3;
        if (cam.equirect) {
          const double max_sigma_u = 0.5 * cam.W / 3.5;
          const double shrink = std::min(1.0, max_sigma_u / std::sqrt(std::max(a, 1e-300)));
          a *= shrink * shrink;
          b *= shrink;
        }
        const double det = a * c - b * b;
        valid = std::isfinite(a) && std::isfinite(b) && std::isfinite(c) && det > 0;
        if (!valid) { a = 1; b = 0; c = 1; }
      }
      const double det = a * c - b * b;
      const double ru = 3.5 * std::sqrt(a), rv = 3.5 * std::sqrt(c);
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
  const int64_t M = m.size(0);
  const double* mp = m.data_ptr<double>();
  const double* rp = r.data_ptr<double>();
  std::vector<int64_t> tx0(M), tx1(M), ty0(M), ty1(M);
  auto offsets = torch::zeros({g.ntx * g.nty + 1}, torch::kInt64);
  int64_t* off = offsets.data_ptr<int64_t>();
  for (int64_t i = 0; i < M; ++i) {
    const double u = mp[2 * i], v = mp[2 * i + 1], ru = rp[2 * i], rv = rp[2 * i + 1];
    ty0[i] = std::clamp<int64_t>((int64_t)std::floor((v - rv) / tile), 0, g.nty - 1);
    ty1[i] = std::clamp<int64_t>((int64_t)std::floor((v + rv) / tile), 0, g.nty - 1);
    double a = std::floor((u - ru) / tile), b = std::floor((u + ru) / tile);
    if (wrap > 0) {
      if (b - a + 1 >= g.ntx) { a = 0; b = g.ntx - 1; }
    } else {
      a = std::clamp<double>(a, 0, g.ntx - 1);
      b = std::clamp<double>(b, 0, g.ntx - 1);
    }
    tx0[i] = (int64_t)a;
    tx1[i] = (int64_t)b;
    for (int64_t ty = ty0[i]; ty <= ty1[i]; ++ty)
      for (int64_t tx = tx0[i]; tx <= tx1[i]; ++tx) {
        const int64_t txw = ((tx % g.ntx) + g.ntx) % g.ntx;
        ++off[ty * g.ntx + txw + 1];
      }
  }
  for (int64_t t = 0; t < g.ntx * g.nty; ++t) off[t + 1] += off[t];
  auto ids = torch::empty({off[g.ntx * g.nty]}, torch::kInt64);
  int64_t* ip = ids.data_ptr<int64_t>();
  std::vector<int64_t> fill(off, off + g.ntx * g.nty);
  for (int64_t i = 0; i < M; ++i)
    for (int64_t ty = ty0[i]; ty <= ty1[i]; ++ty)
      for (int64_t tx = tx0[i]; tx <= tx1[i]; ++tx) {
        const int64_t txw = ((tx % g.ntx) + g.ntx) % g.ntx;
        ip[fill[ty * g.ntx + txw]++] = i;
      }
  return {offsets, ids};
}

std::vector<torch::Tensor> rasterize_forward(torch::Tensor means2d, torch::Tensor radii, torch::Tensor conics, torch::Tensor opac,
                                             torch::Tensor vals, torch::Tensor bg, torch::Tensor offsets,
                                             torch::Tensor ids, int64_t H, int64_t W, double wrap, int64_t tile) {
  const Grid g = make_grid(H, W, tile, wrap);
  const int64_t D = vals.size(1);
  auto opts = vals.options();
  auto out = torch::empty({D, H, W}, opts);
  auto alpha = torch::empty({1, H, W}, opts);
  auto t_final = torch::empty({H, W}, opts.dtype(torch::kFloat64));
  auto n_contrib = torch::empty({H, W}, opts.dtype(torch::kInt64));
  AT_DISPATCH_FLOATING_TYPES(vals.scalar_type(), "splat_cpu_forward", [&] {
    forward_impl<scalar_t>(means2d.data_ptr<scalar_t>(), radii.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                           vals.data_ptr<scalar_t>(), bg.data_ptr<scalar_t>(), D, offsets.data_ptr<int64_t>(),
                           ids.data_ptr<int64_t>(), g, out.data_ptr<scalar_t>(), alpha.data_ptr<scalar_t>(),
                           t_final.data_ptr<double>(), n_contrib.data_ptr<int64_t>());
  });
  return {out, alpha, t_final, n_contrib};
}

std::vector<torch::Tensor> rasterize_backward(torch::Tensor means2d, torch::Tensor radii, torch::Tensor conics, torch::Tensor opac,
                                              torch::Tensor vals, torch::Tensor bg, torch::Tensor offsets,
                                              torch::Tensor ids, int64_t H, int64_t W, double wrap, int64_t tile,
                                              torch::Tensor alpha, torch::Tensor t_final, torch::Tensor n_contrib,
                                              torch::Tensor g_out, torch::Tensor g_alpha) {
  const Grid g = make_grid(H, W, tile, wrap);
  const int64_t D = vals.size(1);
  auto d_mean = torch::zeros_like(means2d);
  auto d_conic = torch::zeros_like(conics);
  auto d_opac = torch::zeros_like(opac);
  auto d_vals = torch::zeros_like(vals);
  const int64_t nthreads = at::get_num_threads();
  auto d_bg_threads = torch::zeros({nthreads, D}, vals.options().dtype(torch::kFloat64));
  AT_DISPATCH_FLOATING_TYPES(vals.scalar_type(), "splat_cpu_backward", [&] {
    backward_impl<scalar_t>(means2d.data_ptr<scalar_t>(), radii.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
                            vals.data_ptr<scalar_t>(), bg.data_ptr<scalar_t>(), D, offsets.data_ptr<int64_t>(),
                            ids.data_ptr<int64_t>(), g, alpha.data_ptr<scalar_t>(), t_final.data_ptr<double>(),
                            n_contrib.data_ptr<int64_t>(), g_out.data_ptr<scalar_t>(), g_alpha.data_ptr<scalar_t>(),
                            d_mean.data_ptr<scalar_t>(), d_conic.data_ptr<scalar_t>(), d_opac.data_ptr<scalar_t>(),
                            d_vals.data_ptr<scalar_t>(), d_bg_threads.data_ptr<double>());
  });
  auto d_bg = d_bg_threads.sum(0).to(vals.scalar_type());
  return {d_mean, d_conic, d_opac, d_vals, d_bg};
}

std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor scales, torch::Tensor quats,
                                           torch::Tensor opac, torch::Tensor finite_mask, torch::Tensor c2w,
                                           bool equirect, double fx, double fy, double cx, double cy, int64_t H,
                                           int64_t W, double near, double far) {
  const int64_t N = means.size(0);
  auto opts = means.options();
  auto uv = torch::empty({N, 2}, opts), conic = torch::empty({N, 3}, opts), cov = torch::empty({N, 3}, opts);
  auto depth = torch::empty({N}, opts), radii = torch::empty({N, 2}, opts);
  auto valid = torch::empty({N}, opts.dtype(torch::kBool));
  auto pose = c2w.to(torch::kFloat64).contiguous();
  const CamParams cam{equirect, fx, fy, cx, cy, H, W, near, far};
  const bool* mask = finite_mask.numel() ? finite_mask.data_ptr<bool>() : nullptr;
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "splat_cpu_project", [&] {
    project_impl<scalar_t>(means.data_ptr<scalar_t>(), scales.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                           opac.data_ptr<scalar_t>(), mask, pose.data_ptr<double>(), cam, N,
                           uv.data_ptr<scalar_t>(), conic.data_ptr<scalar_t>(), cov.data_ptr<scalar_t>(),
                           depth.data_ptr<scalar_t>(), radii.data_ptr<scalar_t>(), valid.data_ptr<bool>());
  });
  return {uv, conic, cov, depth, radii, valid};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("project_forward", &project_forward, "fused inference-only projection");
  m.def("bin_gaussians", &bin_gaussians, "per-tile depth-ordered Gaussian lists");
  m.def("rasterize_forward", &rasterize_forward, "tile-parallel forward rasterisation");
  m.def("rasterize_backward", &rasterize_backward, "tile-parallel backward rasterisation");
}
