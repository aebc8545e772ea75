/* Where pixel rays leave or enter a box (phigenesis/data/native.py).
 *
 * The depth projection's moving-vehicle occluders (stages/project.py, vehicle_far_depth) test
 * every ray of a box's footprint against the box: numpy's slab test makes some fifteen passes
 * over (P, 3) float64 temporaries (0.26 s for a footprint of ~700k rays); this is one pass with
 * the same arithmetic in the same order (camera_tables.ray_box_depths). The ego body's depth
 * (where each pixel's ray enters it, once per calibration) is the same test's entry side.
 */
#include <math.h>
#include <stdint.h>

/* The slab test of one ray (camera_tables.ray_box_depths): 1 if it meets the box, with its
 * entry (clamped at 0: the camera inside) and exit depths. */
static int ray_box(const double *ray, const double *m, const double *half, double *entry,
                   double *exit) {
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
    const double start = t_near > 0.0 ? t_near : 0.0;
    if (!(isfinite(t_near) && isfinite(t_far) && t_far >= start)) return 0;
    *entry = start;
    *exit = t_far;
    return 1;
}

/* rays: (n, 3) float64 camera-frame rays (z = 1); box_from_camera and half as below. For
 * every ray that meets the box, near[p] becomes min(near[p], entry depth) rounded to float32
 * (the ego body's depth, camera_tables.ego_body_depth_from_rays). Returns the rays that hit. */
int64_t phigenesis_ray_box_near(const double *rays, int64_t n, const double *box_from_camera,
                                const double *half, float *near) {
    int64_t hits = 0;
    for (int64_t p = 0; p < n; ++p) {
        double entry, exit;
        if (ray_box(rays + 3 * p, box_from_camera, half, &entry, &exit)) {
            if (entry < (double)near[p]) near[p] = (float)entry;
            ++hits;
        }
    }
    return hits;
}

/* rays: (H * W, 3) float64 camera-frame rays (z = 1), row-major; box_from_camera: 3 x 4
 * float64 row-major (rotation, translation); half: the box's half sizes. For every pixel of
 * rows [r0, r1) and columns [c0, c1) whose ray meets the box (entry at t >= 0 or inside), far
 * becomes min(far, exit depth), rounded to float32. Returns the number of rays that hit. */
int64_t phigenesis_ray_box_far(const double *rays, int64_t width, int64_t r0, int64_t r1,
                               int64_t c0, int64_t c1, const double *box_from_camera,
                               const double *half, float *far) {
    int64_t hits = 0;
    for (int64_t r = r0; r < r1; ++r) {
        for (int64_t c = c0; c < c1; ++c) {
            const int64_t p = r * width + c;
            double entry, exit;
            if (ray_box(rays + 3 * p, box_from_camera, half, &entry, &exit)) {
                if (exit < (double)far[p]) far[p] = (float)exit;
                ++hits;
            }
        }
    }
    return hits;
}
