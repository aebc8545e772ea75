// Native CPU EWA projection of N Gaussians into C pinhole cameras, and its backward pass.
//
// Forward (`project_forward`): the same Projection (means2d, conics, depths, radii, valid) as the PyTorch
// reference `_project_gaussians_torch` in phigenesis/models/rasterizer.py, with the same formulas evaluated
// in the same order and precision (float32 stays float32), so the two agree to the last bit or nearly:
//
//   per Gaussian: R from the wxyz quaternion (zero ones, squared norm <= 1e-24, give the identity;
//                 normalised by 1 / sqrt), M = R diag(clamp(s, +-1e4));
//   per camera:   R_cw = R_wc^T, t_cw = R_cw t_wc, the FoV limits of the Jacobian clamp;
//   per pair:     camera-space mean, z > near, u, v, the clamped Jacobian J, T = J (R_cw M),
//                 Sigma2d = T T^T, det(Sigma2d + eps I) by Cauchy-Binet, the conic, the per-axis box
//                 ceil(extend sqrt(Sigma2d_ii + eps)), and the validity tests.
//
// Floating-point contraction is off in this file (the reference's element-wise ops and small batched
// matmuls round every product and sum); the one exception is the camera-space rotation, an einsum that
// PyTorch hands to a BLAS gemm, which on CPUs with FMA fuses it as fma(r2, p2, fma(r1, p1, r0 p0)),
// except for small problems (fewer than 400 multiply-adds per batched matmul), which PyTorch's own
// loop does unfused: both are mirrored (a BLAS with other kernels costs only last-bit differences).
// Two of the reference's functions are not correctly rounded where PyTorch has MKL (its vector maths
// library, within an ulp): the log of the opacity-aware extend, computed by the caller with PyTorch and
// passed in (N,), and the sqrt of the boxes, which this file hands to PyTorch's sqrt, a chunk at a time.
// Pairs are computed independently, in chunks that torch's threads (at::parallel_for) take from a counter
// (robust to a busy core), so results do not depend on the thread count.
//
// Backward (`project_backward`): the gradients of means, quats and scales from those of means2d, conics
// and depths, what autograd gives through the reference (rasterizer.py's _NativeProjection calls it). It
// recomputes the forward's intermediates (nothing is saved but the inputs) and takes the chain rule back
// through them by hand, with the reference's semantics where they matter for gradients: a zero
// quaternion's identity and a scale outside +-MAX_SCALE get none; z_safe = 1 for z <= near (u, v and the
// Jacobian of a culled Gaussian still pass gradient to x, y, and depths = z passes it to z); the FoV clamp
// of x/z, y/z passes it where it is inactive, half of it at a tie (torch.minimum / torch.maximum), none
// where it is active. Radii and valid have no gradient. Work is split by blocks of Gaussians, each one
// accumulating its cameras' terms in camera order in locals, so there are no atomics and the result does
// not depend on the thread count. It is not bitwise autograd's (other association of the same sums); the
// file's fp-contract=off covers it too, so the forward values it recomputes, which decide the near-plane
// and FoV-clamp tests (a tie included), are bitwise the forward's.

#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>
#include <initializer_list>
#include <type_traits>
#include <utility>
#include <vector>

#pragma GCC push_options
#pragma GCC optimize("fp-contract=off")

namespace phigenesis_native {
namespace {

// The reference's constants (rasterizer.py passes its own), as Python floats; cast to the tensors' dtype
// where the reference's tensor-scalar ops do.
struct Constants {
  double near, eps2d, fov_clamp_margin, max_scale, quaternion_zero_sqnorm;
};

// Runs body(begin, end) over [0, total) in chunks of `chunk`, on torch's threads, chunks taken in order
// from a counter: a thread that starts late (a core busy elsewhere) leaves its share to the others.
template <typename Body>
void for_each_chunk(int64_t total, int64_t chunk, const Body& body) {
  if (total <= 0) return;
  const int64_t chunks = (total + chunk - 1) / chunk;
  std::atomic<int64_t> next{0};
  const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), chunks));
  at::parallel_for(0, workers, 1, [&](int64_t begin, int64_t end) {
    for (int64_t w = begin; w < end; ++w) {
      for (int64_t k = next.fetch_add(1); k < chunks; k = next.fetch_add(1)) {
        body(k * chunk, std::min(total, (k + 1) * chunk));
      }
    }
  });
}

// run(fused, shared) with both flags as std::true_type / std::false_type, for kernels templated on them.
template <typename Run>
inline void with_flags(bool fused, bool shared, const Run& run) {
  using T = std::true_type;
  using F = std::false_type;
  if (fused) {
    shared ? run(T{}, T{}) : run(T{}, F{});
  } else {
    shared ? run(F{}, T{}) : run(F{}, F{});
  }
}

// torch.minimum / torch.maximum: NaN if either is NaN.
template <typename S>
inline S nan_min(S a, S b) {
  const S r = a < b ? a : b;
  return (a == a && b == b) ? r : a + b;
}
template <typename S>
inline S nan_max(S a, S b) {
  const S r = a > b ? a : b;
  return (a == a && b == b) ? r : a + b;
}
template <typename S>
inline bool finite(S x) {
  return std::abs(x) <= std::numeric_limits<S>::max();
}

// std::ceil (up to the sign of a zero result for x = -0) in selects and arithmetic only: GCC vectorizes
// std::ceil only under -fno-trapping-math, which the extension's flags lack. (y + 2^p) - 2^p rounds
// 0 <= y < 2^p to the nearest integer exactly (p = mantissa bits); at and above 2^p (and for inf and
// NaN) y is its own ceil.
template <typename S>
inline S exact_ceil(S x) {
  const S big = static_cast<S>(std::numeric_limits<S>::digits == 24 ? 8388608.0 : 4503599627370496.0);
  const S y = std::abs(x);
  const S t = (y + big) - big;
  const S up = t < y ? t + S(1) : t;    // ceil(y)
  const S down = t > y ? t - S(1) : t;  // floor(y)
  const S r = x < S(0) ? -down : up;
  return y < big ? r : x;
}

// Whether the FMA CPU instructions are there (then BLAS gemm kernels use them).
#ifdef __FMA__
constexpr bool kHaveFma = true;
#else
constexpr bool kHaveFma = false;
#endif

// r0 p0 + r1 p1 + r2 p2 as the reference's einsum rounds it: fused (BLAS) or not (PyTorch's loop).
template <bool kFused, typename S>
inline S dot3(S r0, S r1, S r2, S p0, S p1, S p2) {
  if constexpr (kFused) {
    return std::fma(r2, p2, std::fma(r1, p1, r0 * p0));
  } else {
    return (r0 * p0 + r1 * p1) + r2 * p2;
  }
}

// Whether the reference's rotation einsum is fused (dot3<true>): it is one matmul, (3C x 3) (3 x N), for
// shared centres and C (3 x 3) (3 x N) ones for per-camera centres: PyTorch's unfused loop below 400
// multiply-adds each, else BLAS.
inline bool rotation_is_fused(int64_t n, int64_t cams, bool per_camera) {
  return kHaveFma && 9 * n * (per_camera ? 1 : cams) >= 400;
}

template <typename S>
struct Camera {
  S r[9];  // R_cw, row-major
  S t[3];  // R_cw t_wc
  S fx, fy, cx, cy, lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg;
};

template <typename S>
Camera<S> camera_constants(const S* pose, const S* k, int64_t width, int64_t height, const Constants& kc) {
  Camera<S> cam;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) cam.r[i * 3 + j] = pose[j * 4 + i];
  const S tw[3] = {pose[3], pose[7], pose[11]};
  for (int i = 0; i < 3; ++i) {
    const S* r = cam.r + i * 3;
    cam.t[i] = (r[0] * tw[0] + r[1] * tw[1]) + r[2] * tw[2];
  }
  cam.fx = k[0], cam.fy = k[4], cam.cx = k[2], cam.cy = k[5];
  const S margin = static_cast<S>(kc.fov_clamp_margin);
  // tan = 0.5 * size / f is evaluated by PyTorch as reciprocal(f) * (0.5 * size).
  const S tan_x = (S(1) / cam.fx) * static_cast<S>(0.5 * static_cast<double>(width));
  const S tan_y = (S(1) / cam.fy) * static_cast<S>(0.5 * static_cast<double>(height));
  cam.lim_x_pos = (static_cast<S>(static_cast<double>(width) - 0.5) - cam.cx) / cam.fx + margin * tan_x;
  cam.lim_x_neg = (cam.cx + S(0.5)) / cam.fx + margin * tan_x;
  cam.lim_y_pos = (static_cast<S>(static_cast<double>(height) - 0.5) - cam.cy) / cam.fy + margin * tan_y;
  cam.lim_y_neg = (cam.cy + S(0.5)) / cam.fy + margin * tan_y;
  return cam;
}

// The wxyz quaternion normalised as the reference does (a zero one, squared norm <= the threshold, is the
// identity), and 1 / its norm (1 for a zero one); whether it was not zero.
template <typename S>
inline bool unit_quaternion(const S* quat, const Constants& kc, S& w, S& x, S& y, S& z, S& inv) {
  w = quat[0], x = quat[1], y = quat[2], z = quat[3];
  S sq = ((w * w + x * x) + y * y) + z * z;
  const bool ok = sq > static_cast<S>(kc.quaternion_zero_sqnorm);
  w = ok ? w : S(1), x = ok ? x : S(0), y = ok ? y : S(0), z = ok ? z : S(0), sq = ok ? sq : S(1);
  inv = S(1) / std::sqrt(sq);
  w = w * inv, x = x * inv, y = y * inv, z = z * inv;
  return ok;
}

// R diag(clamped s) of one Gaussian, row-major, entry k at m[k * stride].
template <typename S>
inline void rotation_scale(const S* quat, const S* scale, S* m, int64_t stride, const Constants& kc) {
  S w, x, y, z, inv;
  unit_quaternion(quat, kc, w, x, y, z, inv);
  const S rot[9] = {
      S(1) - S(2) * (y * y + z * z), S(2) * (x * y - w * z),         S(2) * (x * z + w * y),
      S(2) * (x * y + w * z),         S(1) - S(2) * (x * x + z * z), S(2) * (y * z - w * x),
      S(2) * (x * z - w * y),         S(2) * (y * z + w * x),         S(1) - S(2) * (x * x + y * y),
  };
  const S hi = static_cast<S>(kc.max_scale), lo = -hi;
  for (int j = 0; j < 3; ++j) {
    const S s = nan_min(nan_max(scale[j], lo), hi);
    for (int i = 0; i < 3; ++i) m[(i * 3 + j) * stride] = rot[i * 3 + j] * s;
  }
}

struct Outputs {
  at::Tensor means2d, conics, depths, radii, valid;
};

// Gaussians per block of project_range: computed lane by lane from planes of inputs, in a loop the
// compiler vectorizes, into local arrays, then written out interleaved.
constexpr int64_t kBlock = 32;
// (Camera, Gaussian) pairs per task: its outputs stay in the core's cache between the passes.
constexpr int64_t kChunk = 8192;

// One camera, Gaussians [g0, g1), all but the boxes. `planes` holds, per Gaussian (plane k at
// planes[k * n + g]), the 9 entries of R diag(s) and, for shared centres (kShared), the 3 coordinates of
// the centre; otherwise `pts` is the camera's (N, 3) centres. Writes Sigma2d_ii + eps where the radii go
// and, as valid, the tests so far.
template <bool kFused, bool kShared, typename S>
void project_range(const Camera<S>& cam, const S* pts, const S* planes, int64_t n, int64_t g0, int64_t g1,
                   const Constants& kc, S* o_m2d, S* o_con, S* o_z, S* o_rad, uint8_t* o_valid) {
  const S near = static_cast<S>(kc.near);
  const S eps = static_cast<S>(kc.eps2d), eps_sq = static_cast<S>(kc.eps2d * kc.eps2d);
  const S r0 = cam.r[0], r1 = cam.r[1], r2 = cam.r[2], r3 = cam.r[3], r4 = cam.r[4], r5 = cam.r[5];
  const S r6 = cam.r[6], r7 = cam.r[7], r8 = cam.r[8];
  const S fx = cam.fx, fy = cam.fy, cx = cam.cx, cy = cam.cy, neg_fx = -cam.fx, neg_fy = -cam.fy;
  alignas(64) S in_p[3][kBlock];
  alignas(64) S out_u[kBlock], out_v[kBlock], out_c[3][kBlock], out_z[kBlock], out_a[kBlock], out_b[kBlock];
  alignas(64) bool out_valid[kBlock];
  for (int64_t g = g0; g < g1; g += kBlock) {
    const int64_t len = std::min(kBlock, g1 - g);
    const S *px, *py, *pz;
    if constexpr (kShared) {
      px = planes + 9 * n + g, py = planes + 10 * n + g, pz = planes + 11 * n + g;
    } else {
      for (int64_t l = 0; l < len; ++l) {
        for (int k = 0; k < 3; ++k) in_p[k][l] = pts[(g + l) * 3 + k];
      }
      px = in_p[0], py = in_p[1], pz = in_p[2];
    }
    const S* m = planes + g;
    for (int64_t l = 0; l < len; ++l) {
      const S p0 = px[l], p1 = py[l], p2 = pz[l];
      const S x = dot3<kFused>(r0, r1, r2, p0, p1, p2) - cam.t[0];
      const S y = dot3<kFused>(r3, r4, r5, p0, p1, p2) - cam.t[1];
      const S z = dot3<kFused>(r6, r7, r8, p0, p1, p2) - cam.t[2];
      bool valid = z > near;
      const S zs = valid ? z : S(1);
      const S u = (fx * x) / zs + cx;
      const S v = (fy * y) / zs + cy;
      const S tx = nan_max(nan_min(x / zs, cam.lim_x_pos), -cam.lim_x_neg);
      const S ty = nan_max(nan_min(y / zs, cam.lim_y_pos), -cam.lim_y_neg);
      const S j00 = fx / zs, j02 = (neg_fx * tx) / zs;
      const S j11 = fy / zs, j12 = (neg_fy * ty) / zs;
      // T = J (R_cw M): rows p, q; the zero entries of J are multiplied as the reference's matmul does.
      S pr[3], qr[3];
      for (int j = 0; j < 3; ++j) {
        const S m0 = m[j * n + l], m1 = m[(3 + j) * n + l], m2 = m[(6 + j) * n + l];
        const S rm0 = (r0 * m0 + r1 * m1) + r2 * m2;
        const S rm1 = (r3 * m0 + r4 * m1) + r5 * m2;
        const S rm2 = (r6 * m0 + r7 * m1) + r8 * m2;
        pr[j] = (j00 * rm0 + S(0) * rm1) + j02 * rm2;
        qr[j] = (S(0) * rm0 + j11 * rm1) + j12 * rm2;
      }
      S a = (pr[0] * pr[0] + pr[1] * pr[1]) + pr[2] * pr[2];
      const S b = (pr[0] * qr[0] + pr[1] * qr[1]) + pr[2] * qr[2];
      S c = (qr[0] * qr[0] + qr[1] * qr[1]) + qr[2] * qr[2];
      const S m01 = pr[0] * qr[1] - pr[1] * qr[0];
      const S m02 = pr[0] * qr[2] - pr[2] * qr[0];
      const S m12 = pr[1] * qr[2] - pr[2] * qr[1];
      const S det = (((m01 * m01 + m02 * m02) + m12 * m12) + eps * (a + c)) + eps_sq;
      a = a + eps, c = c + eps;
      const S con0 = c / det, con1 = -b / det, con2 = a / det;
      // Non-short-circuit & keeps the loop free of branches (so it vectorizes).
      valid = valid & finite(u) & finite(v) & finite(con0) & finite(con1) & finite(con2);
      out_u[l] = u, out_v[l] = v, out_z[l] = z;
      out_c[0][l] = con0, out_c[1][l] = con1, out_c[2][l] = con2;
      out_a[l] = a, out_b[l] = c;
      out_valid[l] = valid;
    }
    for (int64_t l = 0; l < len; ++l) {
      const int64_t i = g + l;
      o_m2d[i * 2] = out_u[l], o_m2d[i * 2 + 1] = out_v[l];
      o_con[i * 3] = out_c[0][l], o_con[i * 3 + 1] = out_c[1][l], o_con[i * 3 + 2] = out_c[2][l];
      o_z[i] = out_z[l];
      o_rad[i * 2] = out_a[l], o_rad[i * 2 + 1] = out_b[l];
      o_valid[i] = static_cast<uint8_t>(out_valid[l]);
    }
  }
}

// The boxes of one camera's Gaussians [g0, g1), once `o_rad` holds sqrt(Sigma2d_ii + eps):
// ceil(extend sqrt(.)) and the remaining validity tests (finite, non-empty, on screen); 0 if culled.
template <typename S>
void finish_range(const S* extend, int64_t g0, int64_t g1, S width_last, S height_last, const S* o_m2d, S* o_rad,
                  uint8_t* o_valid) {
  alignas(64) S ok[kBlock];  // the validity flags as S, so that the loop over them is all of one width
  for (int64_t g = g0; g < g1; g += kBlock) {
    const int64_t len = std::min(kBlock, g1 - g);
    for (int64_t l = 0; l < len; ++l) ok[l] = o_valid[g + l] ? S(1) : S(0);
    for (int64_t l = 0; l < len; ++l) {
      const int64_t i = g + l;
      const S rx = exact_ceil(extend[i] * o_rad[i * 2]), ry = exact_ceil(extend[i] * o_rad[i * 2 + 1]);
      const S u = o_m2d[i * 2], v = o_m2d[i * 2 + 1];
      bool valid = (ok[l] != S(0)) & finite(rx) & finite(ry) & (rx > S(0)) & (ry > S(0));
      valid = valid & (u + rx >= S(0)) & (u - rx <= width_last) & (v + ry >= S(0)) & (v - ry <= height_last);
      o_rad[i * 2] = valid ? rx : S(0), o_rad[i * 2 + 1] = valid ? ry : S(0);
      ok[l] = valid ? S(1) : S(0);
    }
    for (int64_t l = 0; l < len; ++l) o_valid[g + l] = ok[l] != S(0);
  }
}

template <typename S>
Outputs project_impl(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                     const at::Tensor& world_from_camera, const at::Tensor& intrinsics, const at::Tensor& extend,
                     int64_t width, int64_t height, const Constants& kc) {
  const int64_t cams = world_from_camera.size(0), n = quats.size(0);
  const bool per_camera = means.dim() == 3;
  const auto opts = means.options();
  Outputs out{torch::empty({cams, n, 2}, opts), torch::empty({cams, n, 3}, opts), torch::empty({cams, n}, opts),
              torch::empty({cams, n, 2}, opts), torch::empty({cams, n}, opts.dtype(torch::kBool))};
  if (cams == 0 || n == 0) return out;

  const S* q = quats.data_ptr<S>();
  const S* s = scales.data_ptr<S>();
  const S* pts = means.data_ptr<S>();
  // Per Gaussian, as planes (see project_range): R diag(s), and the shared centres.
  std::vector<S> planes(static_cast<size_t>(n) * (per_camera ? 9 : 12));
  for_each_chunk(n, 8192, [&](int64_t begin, int64_t end) {
    for (int64_t g = begin; g < end; ++g) {
      rotation_scale(q + g * 4, s + g * 3, planes.data() + g, n, kc);
      if (!per_camera) {
        for (int k = 0; k < 3; ++k) planes[(9 + k) * n + g] = pts[g * 3 + k];
      }
    }
  });
  std::vector<Camera<S>> cameras(cams);
  const S* pose = world_from_camera.data_ptr<S>();
  const S* k = intrinsics.data_ptr<S>();
  for (int64_t c = 0; c < cams; ++c) cameras[c] = camera_constants(pose + c * 16, k + c * 9, width, height, kc);

  const S* ext = extend.data_ptr<S>();
  S* o_m2d = out.means2d.data_ptr<S>();
  S* o_con = out.conics.data_ptr<S>();
  S* o_z = out.depths.data_ptr<S>();
  S* o_rad = out.radii.data_ptr<S>();
  // The bool tensor's bytes (0 or 1), as uint8_t: GCC does not vectorize loads of bool.
  uint8_t* o_valid = reinterpret_cast<uint8_t*>(out.valid.data_ptr<bool>());
  const S width_last = static_cast<S>(width - 1), height_last = static_cast<S>(height - 1);
  const bool fused = rotation_is_fused(n, cams, per_camera);
  const auto sqrt_opts = at::TensorOptions().dtype(c10::CppTypeToScalarType<S>::value);
  for_each_chunk(cams * n, kChunk, [&](int64_t begin, int64_t end) {
    // The chunk's (camera, Gaussian range) pieces.
    auto for_pieces = [&](const auto& piece) {
      for (int64_t i = begin; i < end;) {
        const int64_t c = i / n, g0 = i % n, g1 = std::min(n, g0 + (end - i));
        piece(c, g0, g1);
        i += g1 - g0;
      }
    };
    for_pieces([&](int64_t c, int64_t g0, int64_t g1) {
      const int64_t base = c * n;
      const S* p = pts + base * 3;  // per-camera centres only
      auto run = [&](auto fused_tag, auto shared_tag) {
        project_range<decltype(fused_tag)::value, decltype(shared_tag)::value>(
            cameras[c], p, planes.data(), n, g0, g1, kc, o_m2d + base * 2, o_con + base * 3, o_z + base,
            o_rad + base * 2, o_valid + base);
      };
      with_flags(fused, !per_camera, run);
    });
    // PyTorch's own sqrt (with MKL, its vector maths library: within an ulp, not always the correctly
    // rounded std::sqrt), so that the boxes' ceil sees the reference's values; serial here, inside the
    // parallel region.
    at::from_blob(o_rad + begin * 2, {(end - begin) * 2}, sqrt_opts).sqrt_();
    for_pieces([&](int64_t c, int64_t g0, int64_t g1) {
      const int64_t base = c * n;
      finish_range(ext, g0, g1, width_last, height_last, o_m2d + base * 2, o_rad + base * 2, o_valid + base);
    });
  });
  return out;
}


// --- Backward ---------------------------------------------------------------------------------------

// d min(a, b) / d a as torch.minimum's backward has it: 1 below (and for NaN), 1/2 at a tie, 0 above;
// d max(a, b) / d a the mirror image.
template <typename S>
inline S min_share(S a, S b) {
  return a > b ? S(0) : (a == b ? S(0.5) : S(1));
}
template <typename S>
inline S max_share(S a, S b) {
  return a < b ? S(0) : (a == b ? S(0.5) : S(1));
}

// Gaussians per block of backward_range (the lanes of its inner loops).
constexpr int64_t kBackwardBlock = 32;

// The gradients of Gaussians [g0, g1) from every camera's upstream gradients. `pts` is the (N, 3) shared
// centres (kShared) or the (C, N, 3) per-camera ones; gradients of per-camera centres go to
// o_means[(c N + g) 3 + k], of shared ones (summed over the cameras, in camera order) to o_means[g 3 + k].
template <bool kFused, bool kShared, typename S>
void backward_range(const std::vector<Camera<S>>& cameras, const S* pts, const S* quats, const S* scales,
                    int64_t n, int64_t g0, int64_t g1, const Constants& kc, const S* g_m2d, const S* g_con,
                    const S* g_z, S* o_means, S* o_quats, S* o_scales) {
  constexpr int64_t B = kBackwardBlock;
  const S near = static_cast<S>(kc.near);
  const S eps = static_cast<S>(kc.eps2d), eps_sq = static_cast<S>(kc.eps2d * kc.eps2d);
  const S hi = static_cast<S>(kc.max_scale), lo = -hi;
  const int64_t cams = static_cast<int64_t>(cameras.size());
  alignas(64) S m[9][B];                   // R diag(clamped s), row-major
  alignas(64) S in_p[3][B];                // this camera's (or the shared) centres
  alignas(64) S acc_m[9][B], acc_p[3][B];  // gradients of M and of the shared centres
  for (int64_t g = g0; g < g1; g += B) {
    const int64_t len = std::min(B, g1 - g);
    for (int64_t l = 0; l < len; ++l) {
      rotation_scale(quats + (g + l) * 4, scales + (g + l) * 3, &m[0][l], B, kc);
      for (int k = 0; k < 9; ++k) acc_m[k][l] = S(0);
      for (int k = 0; k < 3; ++k) acc_p[k][l] = S(0);
      if constexpr (kShared) {
        for (int k = 0; k < 3; ++k) in_p[k][l] = pts[(g + l) * 3 + k];
      }
    }
    for (int64_t ci = 0; ci < cams; ++ci) {
      const Camera<S>& cam = cameras[ci];
      const S r0 = cam.r[0], r1 = cam.r[1], r2 = cam.r[2], r3 = cam.r[3], r4 = cam.r[4], r5 = cam.r[5];
      const S r6 = cam.r[6], r7 = cam.r[7], r8 = cam.r[8];
      const S fx = cam.fx, fy = cam.fy, neg_fx = -cam.fx, neg_fy = -cam.fy;
      const int64_t base = ci * n + g;  // (camera, first Gaussian of the block) pair
      if constexpr (!kShared) {
        for (int64_t l = 0; l < len; ++l) {
          for (int k = 0; k < 3; ++k) in_p[k][l] = pts[(base + l) * 3 + k];
        }
      }
      const S* gm2d = g_m2d + base * 2;
      const S* gcon = g_con + base * 3;
      const S* gz_in = g_z + base;
      for (int64_t l = 0; l < len; ++l) {
        // The forward, as project_range computes it.
        const S p0 = in_p[0][l], p1 = in_p[1][l], p2 = in_p[2][l];
        const S x = dot3<kFused>(r0, r1, r2, p0, p1, p2) - cam.t[0];
        const S y = dot3<kFused>(r3, r4, r5, p0, p1, p2) - cam.t[1];
        const S z = dot3<kFused>(r6, r7, r8, p0, p1, p2) - cam.t[2];
        const bool in_front = z > near;
        const S zs = in_front ? z : S(1);
        const S rx = x / zs, ry = y / zs;
        const S inner_x = nan_min(rx, cam.lim_x_pos), inner_y = nan_min(ry, cam.lim_y_pos);
        const S tx = nan_max(inner_x, -cam.lim_x_neg), ty = nan_max(inner_y, -cam.lim_y_neg);
        const S j00 = fx / zs, j02 = (neg_fx * tx) / zs;
        const S j11 = fy / zs, j12 = (neg_fy * ty) / zs;
        S w[3][3], pr[3], qr[3];  // W = R_cw M; T = J W, rows pr and qr
        for (int j = 0; j < 3; ++j) {
          const S m0 = m[j][l], m1 = m[3 + j][l], m2 = m[6 + j][l];
          w[0][j] = (r0 * m0 + r1 * m1) + r2 * m2;
          w[1][j] = (r3 * m0 + r4 * m1) + r5 * m2;
          w[2][j] = (r6 * m0 + r7 * m1) + r8 * m2;
          pr[j] = (j00 * w[0][j] + S(0) * w[1][j]) + j02 * w[2][j];
          qr[j] = (S(0) * w[0][j] + j11 * w[1][j]) + j12 * w[2][j];
        }
        const S a = (pr[0] * pr[0] + pr[1] * pr[1]) + pr[2] * pr[2];
        const S b = (pr[0] * qr[0] + pr[1] * qr[1]) + pr[2] * qr[2];
        const S c = (qr[0] * qr[0] + qr[1] * qr[1]) + qr[2] * qr[2];
        const S m01 = pr[0] * qr[1] - pr[1] * qr[0];
        const S m02 = pr[0] * qr[2] - pr[2] * qr[0];
        const S m12 = pr[1] * qr[2] - pr[2] * qr[1];
        const S det = (((m01 * m01 + m02 * m02) + m12 * m12) + eps * (a + c)) + eps_sq;
        const S con0 = (c + eps) / det, con1 = -b / det, con2 = (a + eps) / det;

        // Conics (c + eps, -b, a + eps) / det -> a, b, c, the minors.
        const S gu = gm2d[l * 2], gv = gm2d[l * 2 + 1];
        const S gc0 = gcon[l * 3], gc1 = gcon[l * 3 + 1], gc2 = gcon[l * 3 + 2];
        const S g_det = -((gc0 * con0 + gc1 * con1) + gc2 * con2) / det;
        const S g_a2 = S(2) * (gc2 / det + eps * g_det);  // d/da, doubled: a = p.p
        const S g_c2 = S(2) * (gc0 / det + eps * g_det);
        const S g_b = -gc1 / det;
        const S g01 = S(2) * m01 * g_det, g02 = S(2) * m02 * g_det, g12 = S(2) * m12 * g_det;
        const S gp[3] = {
            ((g_a2 * pr[0] + g_b * qr[0]) + g01 * qr[1]) + g02 * qr[2],
            ((g_a2 * pr[1] + g_b * qr[1]) - g01 * qr[0]) + g12 * qr[2],
            ((g_a2 * pr[2] + g_b * qr[2]) - g02 * qr[0]) - g12 * qr[1],
        };
        const S gq[3] = {
            ((g_c2 * qr[0] + g_b * pr[0]) - g01 * pr[1]) - g02 * pr[2],
            ((g_c2 * qr[1] + g_b * pr[1]) + g01 * pr[0]) - g12 * pr[2],
            ((g_c2 * qr[2] + g_b * pr[2]) + g02 * pr[0]) + g12 * pr[1],
        };
        // T = J W -> J (its non-zero entries) and W; W = R_cw M -> M (summed over the cameras).
        S g_j00 = S(0), g_j02 = S(0), g_j11 = S(0), g_j12 = S(0);
        for (int j = 0; j < 3; ++j) {
          g_j00 = g_j00 + gp[j] * w[0][j];
          g_j02 = g_j02 + gp[j] * w[2][j];
          g_j11 = g_j11 + gq[j] * w[1][j];
          g_j12 = g_j12 + gq[j] * w[2][j];
          const S gw0 = j00 * gp[j], gw1 = j11 * gq[j], gw2 = j02 * gp[j] + j12 * gq[j];
          acc_m[j][l] = acc_m[j][l] + ((r0 * gw0 + r3 * gw1) + r6 * gw2);
          acc_m[3 + j][l] = acc_m[3 + j][l] + ((r1 * gw0 + r4 * gw1) + r7 * gw2);
          acc_m[6 + j][l] = acc_m[6 + j][l] + ((r2 * gw0 + r5 * gw1) + r8 * gw2);
        }
        // J = [[fx, 0, -fx tx], [0, fy, -fy ty]] / z_safe and u, v -> x, y, z_safe, through the clamp.
        const S g_rx = (neg_fx * g_j02 / zs) * min_share(rx, cam.lim_x_pos) * max_share(inner_x, -cam.lim_x_neg);
        const S g_ry = (neg_fy * g_j12 / zs) * min_share(ry, cam.lim_y_pos) * max_share(inner_y, -cam.lim_y_neg);
        const S g_zs = -(((g_j00 * j00 + g_j02 * j02) + g_j11 * j11) + g_j12 * j12) / zs -
                       (gu * (fx * x) + gv * (fy * y)) / (zs * zs) - (g_rx * rx + g_ry * ry) / zs;
        const S gx = (gu * fx + g_rx) / zs;
        const S gy = (gv * fy + g_ry) / zs;
        const S gz = gz_in[l] + (in_front ? g_zs : S(0));  // depths = z; z_safe = z only in front
        // Camera-space mean = R_cw p - t_cw -> p.
        const S gp0 = (r0 * gx + r3 * gy) + r6 * gz;
        const S gp1 = (r1 * gx + r4 * gy) + r7 * gz;
        const S gp2 = (r2 * gx + r5 * gy) + r8 * gz;
        if constexpr (kShared) {
          acc_p[0][l] = acc_p[0][l] + gp0, acc_p[1][l] = acc_p[1][l] + gp1, acc_p[2][l] = acc_p[2][l] + gp2;
        } else {
          o_means[(base + l) * 3] = gp0, o_means[(base + l) * 3 + 1] = gp1, o_means[(base + l) * 3 + 2] = gp2;
        }
      }
    }
    // M = R diag(clamp(s)) -> R and s; R from the normalised quaternion -> the quaternion.
    for (int64_t l = 0; l < len; ++l) {
      const int64_t i = g + l;
      if constexpr (kShared) {
        for (int k = 0; k < 3; ++k) o_means[i * 3 + k] = acc_p[k][l];
      }
      const S* qi = quats + i * 4;
      S w, x, y, z, inv;
      const bool ok = unit_quaternion(qi, kc, w, x, y, z, inv);
      S g_rot[9];
      for (int j = 0; j < 3; ++j) {
        const S s_cl = nan_min(nan_max(scales[i * 3 + j], lo), hi);
        for (int r = 0; r < 3; ++r) g_rot[r * 3 + j] = acc_m[r * 3 + j][l] * s_cl;
      }
      // d M / d s_j = column j of R.
      const S rot[9] = {
          S(1) - S(2) * (y * y + z * z), S(2) * (x * y - w * z),         S(2) * (x * z + w * y),
          S(2) * (x * y + w * z),         S(1) - S(2) * (x * x + z * z), S(2) * (y * z - w * x),
          S(2) * (x * z - w * y),         S(2) * (y * z + w * x),         S(1) - S(2) * (x * x + y * y),
      };
      for (int j = 0; j < 3; ++j) {
        const S s = scales[i * 3 + j];
        const S g_s = (acc_m[j][l] * rot[j] + acc_m[3 + j][l] * rot[3 + j]) + acc_m[6 + j][l] * rot[6 + j];
        o_scales[i * 3 + j] = (s >= lo && s <= hi) ? g_s : S(0);  // clamp: none outside (and for NaN)
      }
      const S* G = g_rot;
      const S gw = S(2) * (((((-z * G[1] + y * G[2]) + z * G[3]) - x * G[5]) - y * G[6]) + x * G[7]);
      const S gx = S(2) * (((((y * G[1] + z * G[2]) + y * G[3]) - w * G[5]) + z * G[6]) + w * G[7]) -
                   S(4) * x * (G[4] + G[8]);
      const S gy = S(2) * (((((x * G[1] + w * G[2]) + x * G[3]) + z * G[5]) - w * G[6]) + z * G[7]) -
                   S(4) * y * (G[0] + G[8]);
      const S gz = S(2) * (((((-w * G[1] + x * G[2]) + w * G[3]) + y * G[5]) + x * G[6]) + y * G[7]) -
                   S(4) * z * (G[0] + G[4]);
      // q / |q| -> q: (g - q_hat (g . q_hat)) / |q|; none to a zero quaternion (the identity stands in).
      const S dot = ((gw * w + gx * x) + gy * y) + gz * z;
      S* oq = o_quats + i * 4;
      oq[0] = ok ? (gw - w * dot) * inv : S(0);
      oq[1] = ok ? (gx - x * dot) * inv : S(0);
      oq[2] = ok ? (gy - y * dot) * inv : S(0);
      oq[3] = ok ? (gz - z * dot) * inv : S(0);
    }
  }
}

template <typename S>
std::vector<at::Tensor> project_backward_impl(const at::Tensor& means, const at::Tensor& quats,
                                              const at::Tensor& scales, const at::Tensor& world_from_camera,
                                              const at::Tensor& intrinsics, const at::Tensor& grad_means2d,
                                              const at::Tensor& grad_conics, const at::Tensor& grad_depths,
                                              int64_t width, int64_t height, const Constants& kc) {
  const int64_t cams = world_from_camera.size(0), n = quats.size(0);
  const bool per_camera = means.dim() == 3;
  at::Tensor g_means = torch::zeros_like(means);
  at::Tensor g_quats = torch::zeros_like(quats), g_scales = torch::zeros_like(scales);
  if (n == 0) return {g_means, g_quats, g_scales};

  std::vector<Camera<S>> cameras(cams);
  const S* pose = world_from_camera.data_ptr<S>();
  const S* k = intrinsics.data_ptr<S>();
  for (int64_t c = 0; c < cams; ++c) cameras[c] = camera_constants(pose + c * 16, k + c * 9, width, height, kc);
  const S* pts = means.data_ptr<S>();
  const S* q = quats.data_ptr<S>();
  const S* s = scales.data_ptr<S>();
  const S* gm2d = grad_means2d.data_ptr<S>();
  const S* gcon = grad_conics.data_ptr<S>();
  const S* gz = grad_depths.data_ptr<S>();
  S* o_means = g_means.data_ptr<S>();
  S* o_quats = g_quats.data_ptr<S>();
  S* o_scales = g_scales.data_ptr<S>();
  const bool fused = rotation_is_fused(n, cams, per_camera);
  // About kChunk (camera, Gaussian) pairs per task, whole blocks of Gaussians.
  const int64_t per_task = std::max<int64_t>(1, kChunk / std::max<int64_t>(1, cams));
  const int64_t chunk = (per_task + kBackwardBlock - 1) / kBackwardBlock * kBackwardBlock;
  for_each_chunk(n, chunk, [&](int64_t g0, int64_t g1) {
    auto run = [&](auto fused_tag, auto shared_tag) {
      backward_range<decltype(fused_tag)::value, decltype(shared_tag)::value>(
          cameras, pts, q, s, n, g0, g1, kc, gm2d, gcon, gz, o_means, o_quats, o_scales);
    };
    with_flags(fused, !per_camera, run);
  });
  return {g_means, g_quats, g_scales};
}

}  // namespace

namespace {

// Checks the inputs every projection entry point takes (`who` names it in the errors); (N, C).
std::pair<int64_t, int64_t> check_inputs(const char* who, const at::Tensor& means, const at::Tensor& quats,
                                         const at::Tensor& scales, const at::Tensor& world_from_camera,
                                         const at::Tensor& intrinsics, std::initializer_list<const at::Tensor*> more) {
  const int64_t n = quats.dim() == 2 ? quats.size(0) : -1;
  const int64_t cams = world_from_camera.dim() == 3 ? world_from_camera.size(0) : -1;
  TORCH_CHECK(n >= 0 && quats.size(1) == 4, who, ": quats must be (N, 4)");
  TORCH_CHECK(cams >= 0 && world_from_camera.size(1) == 4 && world_from_camera.size(2) == 4, who,
              ": world_from_camera must be (C, 4, 4)");
  TORCH_CHECK(means.sizes() == at::IntArrayRef({n, 3}) || means.sizes() == at::IntArrayRef({cams, n, 3}), who,
              ": means must be (N, 3) or (C, N, 3)");
  TORCH_CHECK(scales.sizes() == at::IntArrayRef({n, 3}), who, ": scales must be (N, 3)");
  TORCH_CHECK(intrinsics.sizes() == at::IntArrayRef({cams, 3, 3}), who, ": intrinsics must be (C, 3, 3)");
  TORCH_CHECK(n < (int64_t(1) << 31), who, ": at most 2^31 - 1 Gaussians");
  std::vector<const at::Tensor*> all{&means, &quats, &scales, &world_from_camera, &intrinsics};
  all.insert(all.end(), more.begin(), more.end());
  for (const at::Tensor* t : all) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous(), who, ": tensors must be contiguous, on the CPU");
    TORCH_CHECK(t->scalar_type() == means.scalar_type(), who, ": tensors must share one dtype");
  }
  TORCH_CHECK(means.scalar_type() == torch::kFloat || means.scalar_type() == torch::kDouble, who,
              ": float32 or float64 tensors");
  return {n, cams};
}

}  // namespace

std::vector<at::Tensor> project_forward(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                        const at::Tensor& world_from_camera, const at::Tensor& intrinsics,
                                        const at::Tensor& extend, int64_t width, int64_t height, double near,
                                        double eps2d, double fov_clamp_margin, double max_scale,
                                        double quaternion_zero_sqnorm) {
  const auto [n, cams] = check_inputs("project_cpu", means, quats, scales, world_from_camera, intrinsics, {&extend});
  (void)cams;
  TORCH_CHECK(extend.sizes() == at::IntArrayRef({n}), "project_cpu: extend must be (N,)");
  const Constants kc{near, eps2d, fov_clamp_margin, max_scale, quaternion_zero_sqnorm};
  Outputs out;
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_cpu", [&] {
    out = project_impl<scalar_t>(means, quats, scales, world_from_camera, intrinsics, extend, width, height, kc);
  });
  return {out.means2d, out.conics, out.depths, out.radii, out.valid};
}

std::vector<at::Tensor> project_backward(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                         const at::Tensor& world_from_camera, const at::Tensor& intrinsics,
                                         const at::Tensor& grad_means2d, const at::Tensor& grad_conics,
                                         const at::Tensor& grad_depths, int64_t width, int64_t height, double near,
                                         double eps2d, double fov_clamp_margin, double max_scale,
                                         double quaternion_zero_sqnorm) {
  const auto [n, cams] = check_inputs("project_backward", means, quats, scales, world_from_camera, intrinsics,
                                      {&grad_means2d, &grad_conics, &grad_depths});
  TORCH_CHECK(grad_means2d.sizes() == at::IntArrayRef({cams, n, 2}),
              "project_backward: grad_means2d must be (C, N, 2)");
  TORCH_CHECK(grad_conics.sizes() == at::IntArrayRef({cams, n, 3}),
              "project_backward: grad_conics must be (C, N, 3)");
  TORCH_CHECK(grad_depths.sizes() == at::IntArrayRef({cams, n}), "project_backward: grad_depths must be (C, N)");
  const Constants kc{near, eps2d, fov_clamp_margin, max_scale, quaternion_zero_sqnorm};
  std::vector<at::Tensor> out;
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward", [&] {
    out = project_backward_impl<scalar_t>(means, quats, scales, world_from_camera, intrinsics, grad_means2d,
                                          grad_conics, grad_depths, width, height, kc);
  });
  return out;
}

}  // namespace phigenesis_native

#pragma GCC pop_options
