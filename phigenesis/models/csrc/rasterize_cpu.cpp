// Native CPU Gaussian rasterizer: tile binning, front-to-back compositing and its backward pass.
//
// The projection (3D Gaussians -> screen-space means, conics, depths, radii) is PyTorch's
// (phigenesis/models/rasterizer.py, differentiable by autograd), with a native twin and its backward in
// project_cpu.cpp (bound here as `project` and `project_backward`); this file does the rest:
//
//   bin:      every (camera, Gaussian) with a non-zero radius goes to each 16x16 tile its per-axis box
//             touches (boxes are clipped to the image, so one Gaussian holds at most every tile); each
//             tile's list is in (camera z, Gaussian index) order, from one sort per camera.
//   forward:  per tile, the Gaussians front to back; each one is evaluated only at the pixel centres
//             inside its box, alpha = min(MAX_ALPHA, o exp(-sigma)), skipped if sigma < 0 or
//             alpha < 1/255, and a pixel stops before the Gaussian that would bring its
//             transmittance to <= 1e-4 (gsplat 1.5.3's conventions). Saves, per pixel, the final
//             transmittance and how many list entries it used.
//   backward: per tile, the same Gaussians back to front (the replay of gsplat and the Inria
//             rasterizer): each pixel's transmittance before a Gaussian is recovered as T / (1 - alpha)
//             and the colour behind it accumulated as it goes. Each tile writes the gradients of its
//             own list entries, so no two threads write the same memory; a second pass adds the
//             entries of each Gaussian, in list order, which makes the result deterministic. Tiles are
//             replayed in chunks of at most kChunkEntries entries, so this buffer stays bounded.
//
// Tiles are handed to threads from an atomic counter (tiles differ a lot in cost), inside
// at::parallel_for, so the thread count is torch's (torch.set_num_threads).
//
// Conventions: pixel (row i, column j) has its centre at (u, v) = (j, i); dx = u_mean - j; the conic
// (A, B, C) gives sigma = A dx^2 / 2 + B dx dy + C dy^2 / 2. Tensors are contiguous and on the CPU.

#include <torch/extension.h>

#include <ATen/Parallel.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr double kMaxAlpha = 0.999;
constexpr double kAlphaThreshold = 1.0 / 255.0;
constexpr double kTransmittanceThreshold = 1e-4;

// Runs body(task) for task in [0, num_tasks) on torch's threads, tasks taken in order from a counter.
template <typename Body>
void for_each_task(int64_t num_tasks, const Body& body) {
  if (num_tasks <= 0) return;
  std::atomic<int64_t> next{0};
  const int64_t workers = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), num_tasks));
  at::parallel_for(0, workers, 1, [&](int64_t begin, int64_t end) {
    for (int64_t w = begin; w < end; ++w) {
      for (int64_t task = next.fetch_add(1); task < num_tasks; task = next.fetch_add(1)) body(task);
    }
  });
}

// Pixel range [lo, hi] whose centres lie within [centre - radius, centre + radius], clamped to
// [0, size - 1]; empty when lo > hi.
inline void pixel_span(double centre, int radius, int64_t size, int64_t& lo, int64_t& hi) {
  const double a = std::ceil(centre - radius), b = std::floor(centre + radius);
  lo = a < 0 ? 0 : (a > size ? size : static_cast<int64_t>(a));
  hi = b > size - 1 ? size - 1 : (b < -1 ? -1 : static_cast<int64_t>(b));
}

// One (camera, Gaussian) that touches a pixel centre, packed for the compositing loops: the slots of
// a camera are contiguous and in depth order, so a tile's list walks memory forwards.
template <typename scalar_t>
struct Splat {
  scalar_t u, v, a, b, c, opacity;
  // Beyond this sigma alpha is surely below 1/255 (ln(255 opacity) plus a margin far above rounding),
  // so exp need not be evaluated; below it, the exact test decides.
  scalar_t sigma_cut;
  scalar_t z;
  int32_t rx, ry, g;
};

struct Binning {
  at::Tensor tile_offsets;  // (C * T + 1) int64: tile k's entries are [offsets[k], offsets[k + 1])
  at::Tensor entries;       // (I,) int32 slot of each entry
  at::Tensor slot_ids;      // (S,) int32 (camera * N + Gaussian) of each slot
};

template <typename scalar_t>
Binning bin_gaussians(const at::Tensor& means2d, const at::Tensor& depths, const at::Tensor& radii,
                      int64_t width, int64_t height, int64_t tile) {
  const int64_t cams = means2d.size(0), n = means2d.size(1);
  const int64_t tiles_x = (width + tile - 1) / tile, tiles_y = (height + tile - 1) / tile;
  const int64_t num_tiles = tiles_x * tiles_y;
  const scalar_t* m2d = means2d.data_ptr<scalar_t>();
  const scalar_t* z = depths.data_ptr<scalar_t>();
  const int32_t* rad = radii.data_ptr<int32_t>();

  // Per camera: the Gaussians that touch a pixel centre, sorted by (depth, index), and the tile
  // rectangle of each; then every tile's count, and the lists filled in that order, so each tile's
  // list comes out sorted with no per-tile sort.
  std::vector<std::vector<int32_t>> order(cams);
  std::vector<int32_t> rect(static_cast<size_t>(cams * n) * 4);
  std::vector<int64_t> counts(static_cast<size_t>(cams * num_tiles), 0);
  for_each_task(cams, [&](int64_t c) {
    int64_t* cnt = counts.data() + c * num_tiles;
    std::vector<int32_t>& ord = order[c];
    for (int64_t g = 0; g < n; ++g) {
      const int64_t cg = c * n + g;
      const int rx = rad[cg * 2], ry = rad[cg * 2 + 1];
      if (rx <= 0 || ry <= 0) continue;
      int64_t j0, j1, i0, i1;
      pixel_span(m2d[cg * 2], rx, width, j0, j1);
      pixel_span(m2d[cg * 2 + 1], ry, height, i0, i1);
      if (j0 > j1 || i0 > i1) continue;
      int32_t* r = rect.data() + cg * 4;
      r[0] = j0 / tile, r[1] = j1 / tile, r[2] = i0 / tile, r[3] = i1 / tile;
      for (int64_t ty = r[2]; ty <= r[3]; ++ty)
        for (int64_t tx = r[0]; tx <= r[1]; ++tx) ++cnt[ty * tiles_x + tx];
      ord.push_back(static_cast<int32_t>(g));
    }
    const scalar_t* zc = z + c * n;
    std::sort(ord.begin(), ord.end(), [zc](int32_t a, int32_t b) {
      return zc[a] < zc[b] || (zc[a] == zc[b] && a < b);
    });
  });
  std::vector<int64_t> slot_base(cams + 1, 0);
  for (int64_t c = 0; c < cams; ++c) slot_base[c + 1] = slot_base[c] + static_cast<int64_t>(order[c].size());
  TORCH_CHECK(slot_base[cams] < (int64_t(1) << 31), "rasterize_cpu: too many visible (camera, Gaussian) pairs");
  auto offsets = torch::empty({cams * num_tiles + 1}, torch::kInt64);
  int64_t* off = offsets.data_ptr<int64_t>();
  off[0] = 0;
  for (int64_t k = 0; k < cams * num_tiles; ++k) off[k + 1] = off[k] + counts[k];
  auto entries = torch::empty({off[cams * num_tiles]}, torch::kInt32);
  auto slot_ids = torch::empty({slot_base[cams]}, torch::kInt32);
  int32_t* ent = entries.data_ptr<int32_t>();
  int32_t* sid = slot_ids.data_ptr<int32_t>();
  for_each_task(cams, [&](int64_t c) {
    std::vector<int64_t> cursor(off + c * num_tiles, off + (c + 1) * num_tiles);
    int64_t slot = slot_base[c];
    for (const int32_t g : order[c]) {
      const int32_t* r = rect.data() + (c * n + g) * 4;
      for (int64_t ty = r[2]; ty <= r[3]; ++ty)
        for (int64_t tx = r[0]; tx <= r[1]; ++tx) ent[cursor[ty * tiles_x + tx]++] = static_cast<int32_t>(slot);
      sid[slot++] = static_cast<int32_t>(c * n + g);
    }
    std::vector<int32_t>().swap(order[c]);
  });
  return {offsets, entries, slot_ids};
}

template <typename scalar_t>
std::vector<Splat<scalar_t>> pack_splats(const at::Tensor& means2d, const at::Tensor& conics,
                                         const at::Tensor& opacities, const at::Tensor& depths,
                                         const at::Tensor& radii, const at::Tensor& slot_ids) {
  const int64_t n = means2d.size(1), slots = slot_ids.size(0);
  const scalar_t *m2d = means2d.data_ptr<scalar_t>(), *con = conics.data_ptr<scalar_t>();
  const scalar_t *opac = opacities.data_ptr<scalar_t>(), *z = depths.data_ptr<scalar_t>();
  const int32_t* rad = radii.data_ptr<int32_t>();
  const int32_t* sid = slot_ids.data_ptr<int32_t>();
  std::vector<Splat<scalar_t>> splats(slots);
  at::parallel_for(0, slots, 4096, [&](int64_t begin, int64_t end) {
    for (int64_t k = begin; k < end; ++k) {
      const int64_t cg = sid[k], g = cg % n;
      Splat<scalar_t>& s = splats[k];
      s.u = m2d[cg * 2], s.v = m2d[cg * 2 + 1];
      s.a = con[cg * 3], s.b = con[cg * 3 + 1], s.c = con[cg * 3 + 2];
      s.opacity = opac[g];
      s.sigma_cut = static_cast<scalar_t>(std::log(255.0 * static_cast<double>(s.opacity)) + 1e-3);
      s.z = z[cg];
      s.rx = rad[cg * 2], s.ry = rad[cg * 2 + 1];
      s.g = static_cast<int32_t>(g);
    }
  });
  return splats;
}

// The pixel box [j0, j1] x [i0, i1] of a splat inside the tile [x0, x1) x [y0, y1); empty when
// j0 > j1 or i0 > i1.
template <typename scalar_t>
inline void splat_box(const Splat<scalar_t>& s, int64_t x0, int64_t x1, int64_t y0, int64_t y1,
                      int64_t width, int64_t height, int64_t& j0, int64_t& j1, int64_t& i0, int64_t& i1) {
  pixel_span(s.u, s.rx, width, j0, j1);
  pixel_span(s.v, s.ry, height, i0, i1);
  j0 = std::max(j0, x0), i0 = std::max(i0, y0);
  j1 = std::min(j1, x1 - 1), i1 = std::min(i1, y1 - 1);
}

template <typename scalar_t>
std::vector<at::Tensor> forward_impl(const at::Tensor& means2d, const at::Tensor& conics,
                                     const at::Tensor& opacities, const at::Tensor& features,
                                     const at::Tensor& depths, const at::Tensor& radii, int64_t width,
                                     int64_t height, int64_t tile) {
  const int64_t cams = means2d.size(0), f = features.size(1), fd = f + 1;
  const int64_t tiles_x = (width + tile - 1) / tile, tiles_y = (height + tile - 1) / tile;
  const int64_t num_tiles = tiles_x * tiles_y;
  Binning bins = bin_gaussians<scalar_t>(means2d, depths, radii, width, height, tile);
  const std::vector<Splat<scalar_t>> splats =
      pack_splats<scalar_t>(means2d, conics, opacities, depths, radii, bins.slot_ids);
  const auto opts = means2d.options();
  auto out_feat = torch::zeros({cams, height, width, f}, opts);
  auto out_depth = torch::zeros({cams, height, width}, opts);
  auto out_alpha = torch::zeros({cams, height, width}, opts);
  auto final_t = torch::ones({cams, height, width}, opts);
  auto used = torch::zeros({cams, height, width}, opts.dtype(torch::kInt32));

  const scalar_t* feat = features.data_ptr<scalar_t>();
  const int64_t* off = bins.tile_offsets.data_ptr<int64_t>();
  const int32_t* ent = bins.entries.data_ptr<int32_t>();
  scalar_t *o_feat = out_feat.data_ptr<scalar_t>(), *o_depth = out_depth.data_ptr<scalar_t>();
  scalar_t *o_alpha = out_alpha.data_ptr<scalar_t>(), *o_t = final_t.data_ptr<scalar_t>();
  int32_t* o_used = used.data_ptr<int32_t>();
  const scalar_t max_alpha = kMaxAlpha, alpha_thr = kAlphaThreshold, t_thr = kTransmittanceThreshold;

  for_each_task(cams * num_tiles, [&](int64_t k) {
    const int64_t begin = off[k], end = off[k + 1];
    if (begin == end) return;
    const int64_t c = k / num_tiles, t = k % num_tiles;
    const int64_t x0 = (t % tiles_x) * tile, y0 = (t / tiles_x) * tile;
    const int64_t x1 = std::min(x0 + tile, width), y1 = std::min(y0 + tile, height);
    const int64_t tw = x1 - x0, pixels = tw * (y1 - y0);
    std::vector<scalar_t> trans(pixels, scalar_t(1)), acc(pixels * fd, scalar_t(0));
    std::vector<int32_t> last(pixels, 0);
    std::vector<uint8_t> done(pixels, 0);
    int64_t alive = pixels;
    for (int64_t e = begin; e < end && alive > 0; ++e) {
      const Splat<scalar_t>& s = splats[ent[e]];
      int64_t j0, j1, i0, i1;
      splat_box(s, x0, x1, y0, y1, width, height, j0, j1, i0, i1);
      const scalar_t* fg = feat + static_cast<int64_t>(s.g) * f;
      for (int64_t i = i0; i <= i1; ++i) {
        const scalar_t dy = s.v - scalar_t(i);
        for (int64_t j = j0; j <= j1; ++j) {
          const int64_t p = (i - y0) * tw + (j - x0);
          if (done[p]) continue;
          const scalar_t dx = s.u - scalar_t(j);
          const scalar_t sigma = scalar_t(0.5) * (s.a * dx * dx + s.c * dy * dy) + s.b * dx * dy;
          if (sigma < 0 || sigma > s.sigma_cut) continue;
          const scalar_t alpha = std::min(max_alpha, s.opacity * std::exp(-sigma));
          if (alpha < alpha_thr) continue;
          const scalar_t next_t = trans[p] * (1 - alpha);
          if (next_t <= t_thr) {
            done[p] = 1;
            --alive;
            continue;
          }
          const scalar_t w = alpha * trans[p];
          scalar_t* ap = acc.data() + p * fd;
          for (int64_t q = 0; q < f; ++q) ap[q] += w * fg[q];
          ap[f] += w * s.z;
          trans[p] = next_t;
          last[p] = static_cast<int32_t>(e - begin + 1);
        }
      }
    }
    for (int64_t i = y0; i < y1; ++i) {
      for (int64_t j = x0; j < x1; ++j) {
        const int64_t p = (i - y0) * tw + (j - x0), pix = (c * height + i) * width + j;
        const scalar_t* ap = acc.data() + p * fd;
        std::copy(ap, ap + f, o_feat + pix * f);
        o_depth[pix] = ap[f];
        o_alpha[pix] = 1 - trans[p];
        o_t[pix] = trans[p];
        o_used[pix] = last[p];
      }
    }
  });
  return {out_feat, out_depth, out_alpha, final_t, used, bins.tile_offsets, bins.entries, bins.slot_ids};
}

// Per slot gradient layout: u, v, A, B, C, opacity, depth, features...
constexpr int64_t kSlotFixed = 7;
// Most list entries whose gradients the backward pass holds at once.
constexpr int64_t kChunkEntries = int64_t(1) << 22;

template <typename scalar_t>
std::vector<at::Tensor> backward_impl(const at::Tensor& means2d, const at::Tensor& conics,
                                      const at::Tensor& opacities, const at::Tensor& features,
                                      const at::Tensor& depths, const at::Tensor& radii,
                                      const at::Tensor& final_t, const at::Tensor& used,
                                      const at::Tensor& tile_offsets, const at::Tensor& entries,
                                      const at::Tensor& slot_ids, const at::Tensor& grad_feat,
                                      const at::Tensor& grad_depth, const at::Tensor& grad_alpha, int64_t width,
                                      int64_t height, int64_t tile) {
  const int64_t cams = means2d.size(0), n = means2d.size(1), f = features.size(1), fd = f + 1;
  const int64_t stride = kSlotFixed + f;
  const int64_t tiles_x = (width + tile - 1) / tile, tiles_y = (height + tile - 1) / tile;
  const int64_t num_tiles = tiles_x * tiles_y;
  const int64_t num_entries = entries.size(0), slots = slot_ids.size(0);
  const auto opts = means2d.options();
  const std::vector<Splat<scalar_t>> splats =
      pack_splats<scalar_t>(means2d, conics, opacities, depths, radii, slot_ids);
  // List entries' gradients go to a buffer of at most kChunkEntries rows: tiles are replayed in
  // chunks that fit, and each chunk is summed into the slots' gradients before the next (memory stays
  // bounded however many entries a scene has).
  const int64_t chunk_rows = std::min<int64_t>(num_entries, kChunkEntries);
  auto entry_grads = torch::empty({std::max<int64_t>(chunk_rows, 1), stride}, opts);
  auto slot_grads = torch::zeros({slots, stride}, opts);

  const scalar_t* feat = features.data_ptr<scalar_t>();
  const scalar_t* t_final = final_t.data_ptr<scalar_t>();
  const int32_t* n_used = used.data_ptr<int32_t>();
  const int64_t* off = tile_offsets.data_ptr<int64_t>();
  const int32_t* ent = entries.data_ptr<int32_t>();
  const scalar_t *gf = grad_feat.data_ptr<scalar_t>(), *gd = grad_depth.data_ptr<scalar_t>();
  const scalar_t* ga = grad_alpha.data_ptr<scalar_t>();
  scalar_t* eg = entry_grads.data_ptr<scalar_t>();  // row = entry - first entry of the chunk
  scalar_t* sg = slot_grads.data_ptr<scalar_t>();
  const scalar_t max_alpha = kMaxAlpha, alpha_thr = kAlphaThreshold;

  auto replay_tile = [&](int64_t k, int64_t chunk_begin) {
    const int64_t begin = off[k], end = off[k + 1];
    if (begin == end) return;
    std::fill(eg + (begin - chunk_begin) * stride, eg + (end - chunk_begin) * stride, scalar_t(0));
    const int64_t c = k / num_tiles, t = k % num_tiles;
    const int64_t x0 = (t % tiles_x) * tile, y0 = (t / tiles_x) * tile;
    const int64_t x1 = std::min(x0 + tile, width), y1 = std::min(y0 + tile, height);
    const int64_t tw = x1 - x0, pixels = tw * (y1 - y0);
    // Per pixel: transmittance (after the entry being replayed), what lies behind it (features and
    // depth), the output gradients, the final transmittance and the entries used.
    std::vector<scalar_t> trans(pixels), behind(pixels * fd, scalar_t(0)), grad(pixels * fd);
    std::vector<scalar_t> grad_a(pixels), t_end(pixels);
    std::vector<int32_t> last(pixels);
    int32_t most = 0;
    for (int64_t i = y0; i < y1; ++i) {
      for (int64_t j = x0; j < x1; ++j) {
        const int64_t p = (i - y0) * tw + (j - x0), pix = (c * height + i) * width + j;
        trans[p] = t_end[p] = t_final[pix];
        last[p] = n_used[pix];
        most = std::max(most, last[p]);
        std::copy(gf + pix * f, gf + pix * f + f, grad.data() + p * fd);
        grad[p * fd + f] = gd[pix];
        grad_a[p] = ga[pix];
      }
    }
    std::vector<scalar_t> g_feat(fd);
    for (int64_t e = begin + most - 1; e >= begin; --e) {
      const Splat<scalar_t>& s = splats[ent[e]];
      const int64_t slot = e - begin;
      int64_t j0, j1, i0, i1;
      splat_box(s, x0, x1, y0, y1, width, height, j0, j1, i0, i1);
      const scalar_t* fg = feat + static_cast<int64_t>(s.g) * f;
      scalar_t g_u = 0, g_v = 0, g_a = 0, g_b = 0, g_c = 0, g_o = 0;
      std::fill(g_feat.begin(), g_feat.end(), scalar_t(0));
      for (int64_t i = i0; i <= i1; ++i) {
        const scalar_t dy = s.v - scalar_t(i);
        for (int64_t j = j0; j <= j1; ++j) {
          const int64_t p = (i - y0) * tw + (j - x0);
          if (slot >= last[p]) continue;
          const scalar_t dx = s.u - scalar_t(j);
          const scalar_t sigma = scalar_t(0.5) * (s.a * dx * dx + s.c * dy * dy) + s.b * dx * dy;
          if (sigma < 0 || sigma > s.sigma_cut) continue;
          const scalar_t vis = std::exp(-sigma);
          const scalar_t raw = s.opacity * vis;
          const scalar_t alpha = std::min(max_alpha, raw);
          if (alpha < alpha_thr) continue;
          const scalar_t ra = 1 / (1 - alpha);
          const scalar_t t_before = trans[p] * ra;
          const scalar_t w = alpha * t_before;
          const scalar_t* gp = grad.data() + p * fd;
          scalar_t* bp = behind.data() + p * fd;
          // d out / d alpha: this entry's own term, minus what it hides behind it; and the alpha
          // output, 1 - T_final, whose T_final holds a factor (1 - alpha).
          scalar_t d_alpha = grad_a[p] * t_end[p] * ra;
          for (int64_t q = 0; q < f; ++q) {
            g_feat[q] += w * gp[q];
            d_alpha += gp[q] * (fg[q] * t_before - bp[q] * ra);
            bp[q] += w * fg[q];
          }
          g_feat[f] += w * gp[f];
          d_alpha += gp[f] * (s.z * t_before - bp[f] * ra);
          bp[f] += w * s.z;
          trans[p] = t_before;
          if (raw <= max_alpha) {  // the cap passes no gradient
            g_o += vis * d_alpha;
            const scalar_t d_sigma = -raw * d_alpha;
            g_a += scalar_t(0.5) * dx * dx * d_sigma;
            g_b += dx * dy * d_sigma;
            g_c += scalar_t(0.5) * dy * dy * d_sigma;
            g_u += (s.a * dx + s.b * dy) * d_sigma;
            g_v += (s.b * dx + s.c * dy) * d_sigma;
          }
        }
      }
      scalar_t* out = eg + (e - chunk_begin) * stride;
      out[0] = g_u, out[1] = g_v, out[2] = g_a, out[3] = g_b, out[4] = g_c, out[5] = g_o;
      out[6] = g_feat[f];
      std::copy(g_feat.begin(), g_feat.begin() + f, out + kSlotFixed);
    }
  };

  const int64_t total_tiles = cams * num_tiles;
  for (int64_t first = 0; first < total_tiles;) {
    // The chunk: tiles [first, last) whose entries fit (a tile alone may hold more: then it is its own
    // chunk and the buffer grows to it).
    int64_t last = first + 1;
    while (last < total_tiles && off[last + 1] - off[first] <= chunk_rows) ++last;
    const int64_t chunk_begin = off[first], chunk_entries = off[last] - chunk_begin;
    if (chunk_entries > entry_grads.size(0)) {
      entry_grads = torch::empty({chunk_entries, stride}, opts);
      eg = entry_grads.data_ptr<scalar_t>();
    }
    for_each_task(last - first, [&](int64_t k) { replay_tile(first + k, chunk_begin); });
    // Sum each slot's entries in list order (deterministic); each thread owns a range of slots and
    // scans the chunk for them.
    const int64_t parts = std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), chunk_entries / 4096 + 1));
    for_each_task(parts, [&](int64_t part) {
      const int64_t lo = slots * part / parts, hi = slots * (part + 1) / parts;
      for (int64_t e = chunk_begin; e < chunk_begin + chunk_entries; ++e) {
        const int64_t slot = ent[e];
        if (slot < lo || slot >= hi) continue;
        const scalar_t* src = eg + (e - chunk_begin) * stride;
        scalar_t* dst = sg + slot * stride;
        for (int64_t q = 0; q < stride; ++q) dst[q] += src[q];
      }
    });
    first = last;
  }

  // Slots to (camera, Gaussian) rows: each row has at most one slot, so this is a scatter.
  auto g_means2d = torch::zeros({cams, n, 2}, opts);
  auto g_conics = torch::zeros({cams, n, 3}, opts);
  auto g_depths = torch::zeros({cams, n}, opts);
  auto g_opac = torch::zeros({cams, n}, opts);
  auto g_feats = torch::zeros({cams, n, f}, opts);
  scalar_t *o_m = g_means2d.data_ptr<scalar_t>(), *o_c = g_conics.data_ptr<scalar_t>();
  scalar_t *o_z = g_depths.data_ptr<scalar_t>(), *o_o = g_opac.data_ptr<scalar_t>();
  scalar_t* o_f = g_feats.data_ptr<scalar_t>();
  const int32_t* sid = slot_ids.data_ptr<int32_t>();
  at::parallel_for(0, slots, 4096, [&](int64_t begin, int64_t end) {
    for (int64_t k = begin; k < end; ++k) {
      const int64_t cg = sid[k];
      const scalar_t* src = sg + k * stride;
      o_m[cg * 2] = src[0], o_m[cg * 2 + 1] = src[1];
      o_c[cg * 3] = src[2], o_c[cg * 3 + 1] = src[3], o_c[cg * 3 + 2] = src[4];
      o_o[cg] = src[5];
      o_z[cg] = src[6];
      std::copy(src + kSlotFixed, src + stride, o_f + cg * f);
    }
  });
  return {g_means2d, g_conics, g_opac.sum(0), g_feats.sum(0), g_depths};
}

void check_inputs(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities,
                  const at::Tensor& features, const at::Tensor& depths, const at::Tensor& radii,
                  int64_t width, int64_t height, int64_t tile) {
  TORCH_CHECK(means2d.device().is_cpu(), "rasterize_cpu: tensors must be on the CPU");
  TORCH_CHECK(means2d.dim() == 3 && means2d.size(2) == 2, "means2d must be (C, N, 2)");
  const int64_t cams = means2d.size(0), n = means2d.size(1);
  TORCH_CHECK(conics.sizes() == at::IntArrayRef({cams, n, 3}), "conics must be (C, N, 3)");
  TORCH_CHECK(opacities.sizes() == at::IntArrayRef({n}), "opacities must be (N,)");
  TORCH_CHECK(features.dim() == 2 && features.size(0) == n, "features must be (N, F)");
  TORCH_CHECK(depths.sizes() == at::IntArrayRef({cams, n}), "depths must be (C, N)");
  TORCH_CHECK(radii.sizes() == at::IntArrayRef({cams, n, 2}) && radii.scalar_type() == torch::kInt32,
              "radii must be (C, N, 2) int32");
  TORCH_CHECK(n < (int64_t(1) << 31), "at most 2^31 - 1 Gaussians");
  TORCH_CHECK(width > 0 && height > 0 && tile > 0, "width, height and tile must be positive");
  for (const at::Tensor* t : {&means2d, &conics, &opacities, &features, &depths, &radii}) {
    TORCH_CHECK(t->is_contiguous(), "rasterize_cpu: inputs must be contiguous");
  }
  for (const at::Tensor* t : {&conics, &opacities, &features, &depths}) {
    TORCH_CHECK(t->scalar_type() == means2d.scalar_type(), "rasterize_cpu: inputs must share one dtype");
  }
}

std::vector<at::Tensor> forward(const at::Tensor& means2d, const at::Tensor& conics,
                                const at::Tensor& opacities, const at::Tensor& features,
                                const at::Tensor& depths, const at::Tensor& radii, int64_t width,
                                int64_t height, int64_t tile) {
  check_inputs(means2d, conics, opacities, features, depths, radii, width, height, tile);
  std::vector<at::Tensor> out;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_cpu_forward", [&] {
    out = forward_impl<scalar_t>(means2d, conics, opacities, features, depths, radii, width, height, tile);
  });
  return out;
}

std::vector<at::Tensor> backward(const at::Tensor& means2d, const at::Tensor& conics,
                                 const at::Tensor& opacities, const at::Tensor& features,
                                 const at::Tensor& depths, const at::Tensor& radii, const at::Tensor& final_t,
                                 const at::Tensor& used, const at::Tensor& tile_offsets,
                                 const at::Tensor& entries, const at::Tensor& slot_ids, const at::Tensor& grad_feat,
                                 const at::Tensor& grad_depth, const at::Tensor& grad_alpha, int64_t width,
                                 int64_t height, int64_t tile) {
  check_inputs(means2d, conics, opacities, features, depths, radii, width, height, tile);
  const int64_t cams = means2d.size(0), f = features.size(1);
  TORCH_CHECK(grad_feat.sizes() == at::IntArrayRef({cams, height, width, f}) && grad_feat.is_contiguous(),
              "grad_feat must be contiguous (C, H, W, F)");
  TORCH_CHECK(grad_depth.sizes() == at::IntArrayRef({cams, height, width}) && grad_depth.is_contiguous(),
              "grad_depth must be contiguous (C, H, W)");
  TORCH_CHECK(grad_alpha.sizes() == at::IntArrayRef({cams, height, width}) && grad_alpha.is_contiguous(),
              "grad_alpha must be contiguous (C, H, W)");
  std::vector<at::Tensor> out;
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "rasterize_cpu_backward", [&] {
    out = backward_impl<scalar_t>(means2d, conics, opacities, features, depths, radii, final_t, used,
                                  tile_offsets, entries, slot_ids, grad_feat, grad_depth, grad_alpha, width,
                                  height, tile);
  });
  return out;
}

}  // namespace

namespace phigenesis_native {
// project_cpu.cpp: the EWA projection.
std::vector<at::Tensor> project_forward(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                        const at::Tensor& world_from_camera, const at::Tensor& intrinsics,
                                        const at::Tensor& extend, int64_t width, int64_t height, double near,
                                        double eps2d, double fov_clamp_margin, double max_scale,
                                        double quaternion_zero_sqnorm);
// project_cpu.cpp: its backward (gradients of means, quats, scales).
std::vector<at::Tensor> project_backward(const at::Tensor& means, const at::Tensor& quats, const at::Tensor& scales,
                                         const at::Tensor& world_from_camera, const at::Tensor& intrinsics,
                                         const at::Tensor& grad_means2d, const at::Tensor& grad_conics,
                                         const at::Tensor& grad_depths, int64_t width, int64_t height, double near,
                                         double eps2d, double fov_clamp_margin, double max_scale,
                                         double quaternion_zero_sqnorm);
}  // namespace phigenesis_native

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "PhiGenesis native CPU Gaussian rasterizer (tile binning, compositing, backward).";
  m.def("forward", &forward,
        "(means2d, conics, opacities, features, depths, radii, width, height, tile) -> "
        "[features, depth_sum, alpha, final_T, used, tile_offsets, entries, slot_ids]");
  m.def("backward", &backward,
        "(..., final_T, used, tile_offsets, entries, slot_ids, grad_features, grad_depth_sum, grad_alpha, "
        "width, height, tile) -> [grad_means2d, grad_conics, grad_opacities, grad_features, grad_depths]");
  m.def("project", &phigenesis_native::project_forward,
        "(means, quats, scales, world_from_camera, intrinsics, extend, width, height, near, eps2d, "
        "fov_clamp_margin, max_scale, quaternion_zero_sqnorm) -> [means2d, conics, depths, radii, valid] "
        "(see project_cpu.cpp)");
  m.def("project_backward", &phigenesis_native::project_backward,
        "(means, quats, scales, world_from_camera, intrinsics, grad_means2d, grad_conics, grad_depths, width, "
        "height, near, eps2d, fov_clamp_margin, max_scale, quaternion_zero_sqnorm) -> "
        "[grad_means, grad_quats, grad_scales] (see project_cpu.cpp)");
  m.def("max_alpha", [] { return kMaxAlpha; });
  m.def("alpha_threshold", [] { return kAlphaThreshold; });
  m.def("transmittance_threshold", [] { return kTransmittanceThreshold; });
}
