/* Far side of a box along pixel rays, over a rectangle of the image (phigenesis/data/native.py).
 *
 * The depth projection's moving-vehicle occluders (stages/project.py, vehicle_far_depth) test
 * every ray of a box's footprint against the box: numpy's slab test makes some fifteen passes
 * over (P, 3) float64 temporaries (0.26 s for a footprint of ~700k rays); this is one pass with
 * the same arithmetic in the same order (camera_tables.ray_box_depths).
 */
#include <math.h>
#include <stdint.h>

/* rays: (H * W, 3) float64 camera-frame rays (z = 1), row-major; box_from_camera: 3 x 4
 * float64 row-major (rotation, translation); half: the box's half sizes. For every pixel of
 * rows [r0, r1) and columns [c0, c1) whose ray meets the box (entry at t >= 0 or inside), far
 * becomes min(far, exit depth), rounded to float32. Returns the number of rays that hit. */
int64_t phigenesis_ray_box_far(const double *rays, int64_t width, int64_t r0, int64_t r1,
                               int64_t c0, int64_t c1, const double *box_from_camera,
                               const double *half, float *far) {
    const double *m = box_from_camera;
    int64_t hits = 0;
    for (int64_t r = r0; r < r1; ++r) {
        for (int64_t c = c0; c < c1; ++c) {
            const int64_t p = r * width + c;
            const double *ray = rays + 3 * p;
            double t_near = NAN, t_far = NAN;
            for (int k = 0; k < 3; ++k) {
                const double d = m[4 * k] * ray[0] + m[4 * k + 1] * ray[1] + m[4 * k + 2] * ray[2];
                const double o = m[4 * k + 3];
                const double t1 = (-half[k] - o) / d, t2 = (half[k] - o) / d;
                double lo, hi; /* np.minimum / np.maximum: NaN if either is */
                if (isnan(t1) || isnan(t2)) {
                    lo = hi = NAN;
                } else {
                    lo = t1 < t2 ? t1 : t2;
                    hi = t1 > t2 ? t1 : t2;
                }
                t_near = fmax(t_near, lo); /* np.fmax / np.fmin: a NaN operand is skipped */
                t_far = fmin(t_far, hi);
            }
            if (isfinite(t_near) && isfinite(t_far) && t_far >= (t_near > 0.0 ? t_near : 0.0)) {
                const double current = (double)far[p];
                if (t_far < current) far[p] = (float)t_far;
                ++hits;
            }
        }
    }
    return hits;
}
