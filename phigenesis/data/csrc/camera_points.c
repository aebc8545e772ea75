/* The depth projection's first pass (phigenesis/data/stages/project.py, camera_pixels): world
 * points into one image, in one pass instead of numpy's dozen over millions of map points.
 *
 * For each point i (float32 world x, y, z at points[3 i ..]): d = p - centre and the camera-frame
 * point q_j = d_0 R_0j + d_1 R_1j + d_2 R_2j (R: world_from_camera's rotation, row-major), in
 * float32 like the reference. It is kept if z = q_2 > min_depth, |q|^2 <= max_range2 and x / z,
 * y / z lie in the bounds (x0, x1, y0, y1) (float32 tests); then in double: x / z, y / z within
 * the distortion model's monotonic radius (r^2 <= max_r2), OpenCV distortion (k1, k2, p1, p2, k3)
 * when has_distortion, u = fx x + s y + cx, v = fy y + cy, inside [-0.5, w - 0.5) x [-0.5, h - 0.5)
 * (counts[0] += 1: projected), pixel = rint(v) * w + rint(u) (clipped); then z < ego[pixel]
 * (else counts[1] += 1) and z < far[pixel] + slack (else counts[2] += 1) where those (h * w)
 * float32 maps are given (non-NULL). Each kept point writes its index, (u, v), z and pixel, in
 * input order. The arithmetic is the numpy reference's, in its order; the float32 rotation may
 * differ from BLAS's in the last bit.
 *
 * Then, where max_per_pixel > 0, a pixel holding more than max_per_pixel such points keeps only
 * those within its front band (z <= zmin * band_scale + band_slack, float32: the visibility
 * test's bound, which the others could never pass) and, of those, a uniform subset of about
 * max_per_pixel when more lie in the band: point i is kept if (hash(i) >> 40) * in_band <
 * max_per_pixel << 24 (splitmix64 of its index: deterministic). counts[3] += each point dropped.
 * Returns how many points were kept. */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <stdlib.h>

/* splitmix64's finaliser of x + its increment: a uniform 64-bit hash of a point's index. */
static uint64_t mix64(uint64_t x) {
    uint64_t z = x + 0x9E3779B97F4A7C15ULL;
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
    return z ^ (z >> 31);
}

/* The thinning described above, over the kept points (compacted in place); -1 without memory. */
static int64_t thin_pixels(int64_t kept, int64_t size, int64_t max_per_pixel, float band_scale, float band_slack,
                           int64_t *index, double *uv, float *z, int64_t *pixel, int64_t *counts) {
    float *zmin = (float *)malloc((size_t)size * sizeof(float));
    int32_t *total = (int32_t *)calloc((size_t)size, sizeof(int32_t));
    int32_t *in_band = (int32_t *)calloc((size_t)size, sizeof(int32_t));
    if (zmin == NULL || total == NULL || in_band == NULL) {
        free(zmin), free(total), free(in_band);
        return -1;
    }
    for (int64_t p = 0; p < size; ++p) zmin[p] = INFINITY;
    for (int64_t j = 0; j < kept; ++j) {
        total[pixel[j]] += 1;
        if (z[j] < zmin[pixel[j]]) zmin[pixel[j]] = z[j];
    }
    for (int64_t j = 0; j < kept; ++j) {
        const int64_t p = pixel[j];
        const float limit = zmin[p] * band_scale + band_slack;
        if (total[p] > max_per_pixel && z[j] <= limit) in_band[p] += 1;
    }
    int64_t out = 0;
    for (int64_t j = 0; j < kept; ++j) {
        const int64_t p = pixel[j];
        if (total[p] > max_per_pixel) {
            const float limit = zmin[p] * band_scale + band_slack;
            const int64_t band = in_band[p];
            const int64_t u = (int64_t)(mix64((uint64_t)index[j]) >> 40);
            if (!(z[j] <= limit) || (band > max_per_pixel && u * band >= (max_per_pixel << 24))) {
                counts[3] += 1;
                continue;
            }
        }
        index[out] = index[j];
        uv[2 * out] = uv[2 * j];
        uv[2 * out + 1] = uv[2 * j + 1];
        z[out] = z[j];
        pixel[out] = pixel[j];
        ++out;
    }
    free(zmin), free(total), free(in_band);
    return out;
}

int64_t phigenesis_camera_points(int64_t n, const float *points, const float *centre, const float *rot,
                                 float min_depth_f, float max_range2_f, const float *bounds,
                                 double min_depth, double max_r2, const double *dist, int64_t has_distortion,
                                 const double *k, int64_t w, int64_t h, const float *ego, const float *far,
                                 float slack, int64_t max_per_pixel, float band_scale, float band_slack,
                                 int64_t *index, double *uv, float *z_out, int64_t *pixel, int64_t *counts) {
    int64_t kept = 0;
    const double k1 = dist[0], k2 = dist[1], p1 = dist[2], p2 = dist[3], k3 = dist[4];
    for (int64_t i = 0; i < n; ++i) {
        const float d0 = points[3 * i] - centre[0];
        const float d1 = points[3 * i + 1] - centre[1];
        const float d2 = points[3 * i + 2] - centre[2];
        const float qx = d0 * rot[0] + d1 * rot[3] + d2 * rot[6];
        const float qy = d0 * rot[1] + d1 * rot[4] + d2 * rot[7];
        const float qz = d0 * rot[2] + d1 * rot[5] + d2 * rot[8];
        if (!(qz > min_depth_f)) continue;
        if (!(qx * qx + qy * qy + qz * qz <= max_range2_f)) continue;
        const float xf = qx / qz, yf = qy / qz;
        if (!(xf >= bounds[0] && xf <= bounds[1] && yf >= bounds[2] && yf <= bounds[3])) continue;
        const double zd = (double)qz;
        if (!(zd > min_depth) || !isfinite(qx) || !isfinite(qy) || !isfinite(qz)) continue;
        double x = (double)qx / zd, y = (double)qy / zd;
        if (has_distortion) {
            const double r2 = x * x + y * y;
            if (!(r2 <= max_r2)) continue;
            const double radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
            const double xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
            const double yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
            x = xd;
            y = yd;
        }
        const double u = k[0] * x + k[1] * y + k[2];
        const double v = k[3] * y + k[4];
        if (!(u >= -0.5 && u < (double)w - 0.5 && v >= -0.5 && v < (double)h - 0.5)) continue;
        counts[0] += 1;
        double col = rint((u + 0.5) - 0.5), row = rint((v + 0.5) - 0.5);
        col = col < 0 ? 0 : (col > (double)(w - 1) ? (double)(w - 1) : col);
        row = row < 0 ? 0 : (row > (double)(h - 1) ? (double)(h - 1) : row);
        const int64_t p = (int64_t)row * w + (int64_t)col;
        if (ego != NULL && !(qz < ego[p])) {
            counts[1] += 1;
            continue;
        }
        if (far != NULL) {
            const float limit = far[p] + slack;
            if (!(qz < limit)) {
                counts[2] += 1;
                continue;
            }
        }
        index[kept] = i;
        uv[2 * kept] = u;
        uv[2 * kept + 1] = v;
        z_out[kept] = qz;
        pixel[kept] = p;
        ++kept;
    }
    if (max_per_pixel > 0) return thin_pixels(kept, w * h, max_per_pixel, band_scale, band_slack, index, uv, z_out, pixel, counts);
    return kept;
}
