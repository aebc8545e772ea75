/* Pseudo labels' box rule (phigenesis/data/stages/semantics.py, box_labels_in_rectangles): which
 * pixels of a rectangle see a point inside one 3D box, in one pass over the rectangle.
 *
 * A pixel (row-major index i of an image w wide) with z-depth d (metres) in [z_lo, z_hi] and
 * d > 0 has the world point p = t + d * R r_i (r_i = (x, y, 1) its camera-frame ray, R, t the
 * camera's world pose); with o = p - c (c the box centre) and l = o B (B the box's rotation, box
 * to world: l is o in the box frame) it is inside if |l0| <= lim[0], |l1| <= lim[1],
 * l2 <= lim[2] and l2 >= lim[3]. An inside pixel whose |o|^2 is below best[i] takes the box:
 * best[i] = |o|^2, labels[i] = cls (boxes overlap: the nearest centre wins, the first of equally
 * near ones). Returns the number of inside pixels. Double precision throughout, the arithmetic
 * of the numpy reference, in the same order. */
#include <stdint.h>

int64_t phigenesis_box_labels(const float *depth, const double *rays, int64_t w, int64_t v0, int64_t v1,
                              int64_t u0, int64_t u1, double z_lo, double z_hi, const double *rot,
                              const double *t, const double *c, const double *box, const double *lim,
                              int64_t cls, uint8_t *labels, double *best) {
    int64_t inside = 0;
    for (int64_t v = v0; v < v1; ++v) {
        for (int64_t u = u0; u < u1; ++u) {
            const int64_t i = v * w + u;
            const double d = (double)depth[i];
            if (!(d > 0.0) || d < z_lo || d > z_hi) continue;
            const double *r = rays + 3 * i;
            double o[3];
            for (int j = 0; j < 3; ++j) {
                const double rw = rot[3 * j] * r[0] + rot[3 * j + 1] * r[1] + rot[3 * j + 2] * r[2];
                o[j] = (t[j] + rw * d) - c[j];
            }
            const double l0 = o[0] * box[0] + o[1] * box[3] + o[2] * box[6];
            const double l1 = o[0] * box[1] + o[1] * box[4] + o[2] * box[7];
            const double l2 = o[0] * box[2] + o[1] * box[5] + o[2] * box[8];
            if (!(l0 <= lim[0] && -l0 <= lim[0] && l1 <= lim[1] && -l1 <= lim[1] && l2 <= lim[2] && l2 >= lim[3]))
                continue;
            ++inside;
            const double dist2 = o[0] * o[0] + o[1] * o[1] + o[2] * o[2];
            if (dist2 < best[i]) {
                best[i] = dist2;
                labels[i] = (uint8_t)cls;
            }
        }
    }
    return inside;
}
