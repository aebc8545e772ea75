/* Depth completion's fine pass on a large image (phigenesis/data/stages/complete.py,
 * _complete_coarse): every fillable pixel of the image whose coarse grid cell was completed takes
 * that cell's plane, intersected with its own ray, in one pass over the image.
 *
 * Pixel i = v * w + u (ray r_i = rays[3 i ..], z = 1, length |r_i|) is in cell
 * ry[v] * w2 + rx[u]; a cell is completed if origin_small[cell] >= min_code. With n, o the
 * cell's plane (n . p + o = 0, float32), denom = r_i . n and z = -o / denom: the pixel is filled
 * if z is finite, min_depth < z <= max_depth and |denom| / |r_i| >= sin_min (the incidence):
 * depth[i] = z, conf[i] = conf_small[cell], origin[i] = origin_small[cell]. Double precision,
 * the arithmetic of the numpy reference in the same order. Returns the number of pixels filled. */
#include <math.h>
#include <stdint.h>

int64_t phigenesis_complete_fine(int64_t h, int64_t w, int64_t w2, const int64_t *ry, const int64_t *rx,
                                 const uint8_t *fillable, const double *rays,
                                 const float *normal_small, const float *offset_small, const float *conf_small,
                                 const uint8_t *origin_small, int64_t min_code, double min_depth,
                                 double max_depth, double sin_min, float *depth, float *conf, uint8_t *origin) {
    int64_t filled = 0;
    for (int64_t v = 0; v < h; ++v) {
        const int64_t row = ry[v] * w2;
        for (int64_t u = 0; u < w; ++u) {
            const int64_t i = v * w + u;
            if (!fillable[i]) continue;
            const int64_t cell = row + rx[u];
            if (origin_small[cell] < min_code) continue;
            const double *r = rays + 3 * i;
            const float *n = normal_small + 3 * cell;
            const double denom = r[0] * (double)n[0] + r[1] * (double)n[1] + r[2] * (double)n[2];
            const double z = (double)(-offset_small[cell]) / denom;
            const double norm = sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]);  /* numpy's order */
            const double sin_incidence = fabs(denom) / norm;
            if (!isfinite(z) || !(z > min_depth) || !(z <= max_depth) || !(sin_incidence >= sin_min)) continue;
            depth[i] = (float)z;
            conf[i] = conf_small[cell];
            origin[i] = origin_small[cell];
            ++filled;
        }
    }
    return filled;
}
