/* The depth projection's window moments (phigenesis/data/stages/project.py,
 * occupied_window_moments): for each of the k occupied pixels (sorted flat indices of an h x w
 * image), the sums of the MOMENT_NAMES moments (n, u, v, uu, vv, uv, y, uy, vy, yy; float64, own
 * (k, 10) row-major) of the occupied pixels of its (2 r + 1)^2 window, each neighbour's moments
 * shifted by its offset (dx, dy) from the pixel (du -> du + dx, dv -> dv + dy).
 *
 * A dense map of the image (pixel -> occupied index + 1, 0 for none) finds the neighbours; the
 * numpy reference searches the sorted indices. Neighbours are added in the reference's order (dy,
 * then dx, ascending) with the same arithmetic, so the sums are the same doubles. Returns 0, or -1
 * if the map could not be allocated. */
#include <stdint.h>
#include <stdlib.h>

int64_t phigenesis_window_moments(int64_t h, int64_t w, int64_t k, const int64_t *occupied,
                                  const double *own, int64_t radius, double *out) {
    int32_t *map = (int32_t *)calloc((size_t)(h * w), sizeof(int32_t));
    if (map == NULL) return -1;
    for (int64_t i = 0; i < k; ++i) map[occupied[i]] = (int32_t)(i + 1);
    for (int64_t i = 0; i < k; ++i) {
        const int64_t row = occupied[i] / w, col = occupied[i] % w;
        double s[10] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
        for (int64_t dy = -radius; dy <= radius; ++dy) {
            const int64_t r = row + dy;
            if (r < 0 || r >= h) continue;
            for (int64_t dx = -radius; dx <= radius; ++dx) {
                const int64_t c = col + dx;
                if (c < 0 || c >= w) continue;
                const int32_t j = map[r * w + c];
                if (j == 0) continue;
                const double *m = own + 10 * (int64_t)(j - 1);
                const double n = m[0], u = m[1], v = m[2], y = m[6];
                const double fx = (double)dx, fy = (double)dy;
                s[0] += n;
                s[1] += m[1] + fx * n;
                s[2] += m[2] + fy * n;
                s[3] += m[3] + (double)(2 * dx) * u + (double)(dx * dx) * n;
                s[4] += m[4] + (double)(2 * dy) * v + (double)(dy * dy) * n;
                s[5] += m[5] + fx * v + fy * u + (double)(dx * dy) * n;
                s[6] += y;
                s[7] += m[7] + fx * y;
                s[8] += m[8] + fy * y;
                s[9] += m[9];
            }
        }
        for (int q = 0; q < 10; ++q) out[10 * i + q] = s[q];
    }
    free(map);
    return 0;
}
