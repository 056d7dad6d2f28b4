// Best-view selection on the CPU: gaussians/views.py `best_view_mask`, Gaussian by Gaussian.
//
// The torch function walks the views one after another and runs a dozen whole-array ops per view
// pair (offsets, norms, candidate masks, gathers), so an 86-panorama house spends ~30 s in it on one
// core. The rule itself is per Gaussian: it is dropped as soon as one other view carves it (saw
// empty space through one of its probe points) or models its surface better, and no decision
// depends on another Gaussian. So here each Gaussian walks the views and stops at the first that
// drops it; the views are read-only maps. Same arithmetic in double as the torch function (camera
// projection of cameras.py, nearest pixel of views.py `_pixel_index`): the masks are equal in the
// parity tests and on the HM3D sample (2.8 M Gaussians); only a point rounding differently onto an
// exact pixel or interval boundary (libm against torch's vectorised atan2 / log) could differ.
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "workers.h"

namespace {

constexpr double kPi = 3.14159265358979323846;

struct ViewData {
  const double* w2c;  // (4, 4) row-major world -> camera
  bool equirect;
  double fx, fy, cx, cy;
  int64_t H, W;
  const float* depth;     // (H, W)
  const float* interval;  // (H, W)
  const float* normals;   // (H, W, 3)
  const float* free;      // (H, W)
  double centre[3];
  double min_angle;
  bool carve;
};

struct Hit {
  int64_t pix;   // row * W + col (nearest pixel, clamped into the image)
  double depth;  // range (equirect) or z (pinhole)
  bool ok;       // in front of the camera and inside the image
};

// ViewMap.look_up: the camera projection of cameras.py and the nearest pixel of `_pixel_index`.
inline Hit look_up(const ViewData& v, const double* p) {
  const double* M = v.w2c;
  const double x = p[0] * M[0] + p[1] * M[1] + p[2] * M[2] + M[3];
  const double y = p[0] * M[4] + p[1] * M[5] + p[2] * M[6] + M[7];
  const double z = p[0] * M[8] + p[1] * M[9] + p[2] * M[10] + M[11];
  Hit h;
  double u, w;
  if (v.equirect) {
    h.depth = std::sqrt(x * x + y * y + z * z);
    const double lon = std::atan2(x, z);
    const double lat = std::atan2(-y, std::sqrt(x * x + z * z));
    u = (lon + kPi) * (static_cast<double>(v.W) / (2.0 * kPi));
    w = (0.5 * kPi - lat) * (static_cast<double>(v.H) / kPi);
    const double Wd = static_cast<double>(v.W);
    u = u - Wd * std::floor(u / Wd);  // torch.remainder
    if (u >= Wd) u -= Wd;
    // A non-finite point (NaN range) is never ok; its pixel is only read, never used.
    h.ok = h.depth > 0;
    if (!(std::isfinite(u) && std::isfinite(w))) {
      h.ok = false;
      h.pix = 0;
      return h;
    }
    const int64_t col = std::clamp<int64_t>(static_cast<int64_t>(std::floor(u)), 0, v.W - 1);
    const int64_t row = std::clamp<int64_t>(static_cast<int64_t>(std::floor(w)), 0, v.H - 1);
    h.pix = row * v.W + col;
    return h;
  }
  const bool front = z > 0;
  const double zs = front ? z : 1.0;
  u = v.fx * x / zs + v.cx;
  w = v.fy * y / zs + v.cy;
  h.depth = z;
  // Tested in double: floor() of a far off-image (or NaN) coordinate may not fit an int64. Outside
  // the image the pixel is only read, never used.
  const double fu = std::floor(u), fw = std::floor(w);
  const bool inside = fu >= 0 && fu < static_cast<double>(v.W) && fw >= 0 && fw < static_cast<double>(v.H);
  h.ok = front && inside;
  h.pix = inside ? static_cast<int64_t>(fw) * v.W + static_cast<int64_t>(fu) : 0;
  return h;
}

inline double quantise(double interval, double log_step) { return std::floor(std::log(interval) / log_step); }

// True when the Gaussian survives every view (see best_view_mask in views.py for the rule). A
// Gaussian is dropped when any view drops it, so the order of the tests does not change the result:
// the cheap better-view test runs over all views first, and only its survivors pay for the carving
// look-ups (one per probe point and carving view).
bool keeps(const double* probes, int64_t n_probes, double own_iv, const double* facing, int64_t own,
           const std::vector<ViewData>& views, double tol, double log_step, double owner_cos) {
  const double* mean = probes;  // probe 0 is the centre
  const int64_t n_views = static_cast<int64_t>(views.size());
  for (int64_t i = 0; i < n_views; ++i) {
    if (i == own) continue;
    const ViewData& v = views[i];
    const double off[3] = {v.centre[0] - mean[0], v.centre[1] - mean[1], v.centre[2] - mean[2]};
    const double dist = std::sqrt(off[0] * off[0] + off[1] * off[1] + off[2] * off[2]);
    if (!(dist * v.min_angle <= own_iv)) continue;
    if (!(off[0] * facing[0] + off[1] * facing[1] + off[2] * facing[2] > 0)) continue;
    const Hit h = look_up(v, mean);
    const double d = v.depth[h.pix];
    double iv = v.interval[h.pix];
    const bool same = h.ok && d > 0 && std::abs(h.depth - d) <= tol * d + 2.0 * iv;
    if (!same) continue;
    if (owner_cos > 0) {
      const float* nrm = v.normals + 3 * h.pix;
      const double s = std::max(dist, 1e-12);
      const double c = nrm[0] * (off[0] / s) + nrm[1] * (off[1] / s) + nrm[2] * (off[2] / s);
      if (!(std::abs(c) >= owner_cos)) continue;
    }
    double theirs = own_iv;
    if (log_step > 0) {  // step > 1: intervals compared by quantised level
      iv = quantise(iv, log_step);
      theirs = quantise(theirs, log_step);
    }
    if (iv < theirs || (iv == theirs && i < own)) return false;
  }
  for (int64_t i = 0; i < n_views; ++i) {
    const ViewData& v = views[i];
    if (i == own || !v.carve) continue;
    for (int64_t k = 0; k < n_probes; ++k) {
      const Hit h = look_up(v, probes + 3 * k);
      if (!h.ok) continue;
      const double fr = v.free[h.pix], iv = v.interval[h.pix];
      if (fr > 0 && h.depth < fr - (tol * fr + 2.0 * iv)) return false;
    }
  }
  return true;
}

}  // namespace

// probes (N, P, 3) float64 (probe 0 = the mean), own_iv (N,) float64, facing (N, 3) float64 (unit,
// towards the own camera where the normal is unknown); per view: w2c (4, 4) float64, camera row
// [equirect, fx, fy, cx, cy] float64, depth / interval / free (H, W) and normals (H, W, 3) float32,
// centre (3,) float64, the smallest pixel angle and whether it carves. Returns keep (N,) bool.
torch::Tensor best_view_mask_cpu(torch::Tensor probes, torch::Tensor own_iv, torch::Tensor facing, int64_t own,
                                 std::vector<torch::Tensor> w2c, torch::Tensor cameras,
                                 std::vector<torch::Tensor> depth, std::vector<torch::Tensor> interval,
                                 std::vector<torch::Tensor> normals, std::vector<torch::Tensor> free,
                                 torch::Tensor centres, torch::Tensor min_angle, torch::Tensor carve, double tol,
                                 double step, double owner_cos, int64_t threads) {
  TORCH_CHECK(probes.dim() == 3 && probes.size(2) == 3 && probes.scalar_type() == torch::kFloat64,
              "best_view_mask_cpu: probes must be (N, P, 3) float64");
  const int64_t n = probes.size(0), n_probes = probes.size(1), n_views = static_cast<int64_t>(w2c.size());
  TORCH_CHECK(own_iv.numel() == n && facing.numel() == 3 * n, "best_view_mask_cpu: per-Gaussian shapes differ");
  TORCH_CHECK(cameras.size(0) == n_views && depth.size() == static_cast<size_t>(n_views) &&
                  interval.size() == depth.size() && normals.size() == depth.size() &&
                  free.size() == depth.size() && centres.size(0) == n_views && min_angle.numel() == n_views &&
                  carve.numel() == n_views,
              "best_view_mask_cpu: per-view inputs differ in length");
  auto P = probes.contiguous();
  auto IV = own_iv.to(torch::kFloat64).contiguous();
  auto FA = facing.to(torch::kFloat64).contiguous();
  auto CAM = cameras.to(torch::kFloat64).contiguous();
  auto CEN = centres.to(torch::kFloat64).contiguous();
  auto ANG = min_angle.to(torch::kFloat64).contiguous();
  auto CAR = carve.to(torch::kBool).contiguous();
  std::vector<torch::Tensor> hold;  // keeps the contiguous copies alive
  std::vector<ViewData> views(n_views);
  for (int64_t i = 0; i < n_views; ++i) {
    auto m = w2c[i].to(torch::kFloat64).contiguous();
    auto d = depth[i].to(torch::kFloat32).contiguous();
    auto iv = interval[i].to(torch::kFloat32).contiguous();
    auto nr = normals[i].to(torch::kFloat32).contiguous();
    auto fr = free[i].to(torch::kFloat32).contiguous();
    TORCH_CHECK(d.dim() == 2 && iv.sizes() == d.sizes() && fr.sizes() == d.sizes() && nr.dim() == 3 &&
                    nr.size(0) == d.size(0) && nr.size(1) == d.size(1) && nr.size(2) == 3,
                "best_view_mask_cpu: view ", i, ": maps must be (H, W) and normals (H, W, 3)");
    hold.insert(hold.end(), {m, d, iv, nr, fr});
    const double* cam = CAM.data_ptr<double>() + i * CAM.size(1);
    ViewData& v = views[i];
    v.w2c = m.data_ptr<double>();
    v.equirect = cam[0] != 0;
    v.fx = cam[1];
    v.fy = cam[2];
    v.cx = cam[3];
    v.cy = cam[4];
    v.H = d.size(0);
    v.W = d.size(1);
    v.depth = d.data_ptr<float>();
    v.interval = iv.data_ptr<float>();
    v.normals = nr.data_ptr<float>();
    v.free = fr.data_ptr<float>();
    for (int k = 0; k < 3; ++k) v.centre[k] = CEN.data_ptr<double>()[3 * i + k];
    v.min_angle = ANG.data_ptr<double>()[i];
    v.carve = CAR.data_ptr<bool>()[i];
  }
  auto keep = torch::empty({n}, torch::kBool);
  bool* out = keep.data_ptr<bool>();
  const double* pp = P.data_ptr<double>();
  const double* ivp = IV.data_ptr<double>();
  const double* fp = FA.data_ptr<double>();
  const double log_step = std::log(step);  // once, not per Gaussian
  auto body = [&](int64_t b, int64_t e) {
    for (int64_t g = b; g < e; ++g)
      out[g] = keeps(pp + 3 * n_probes * g, n_probes, ivp[g], fp + 3 * g, own, views, tol, log_step, owner_cos);
  };
  image2sim_workers::parallel_range(n, 4096, threads, body);
  return keep;
}
