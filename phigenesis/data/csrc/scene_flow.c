/* Scene flow's pixel pass (phigenesis/data/stages/flow.py, camera_flow): every pixel of a moving
 * box's rectangle whose point lies inside the box takes the box's rigid flow, in one pass over the
 * rectangle.
 *
 * A pixel (row-major index i of an image w wide) with z-depth d (metres) in (z_near, z_far] has the
 * camera-frame point d r_i (r_i = (x, y, 1) its undistorted ray); with o = d r_i - c (c the box
 * centre in the camera frame) and l = o B (B the box's rotation, box to camera: l is o in the box
 * frame) it is inside if |l0| <= lim[0], |l1| <= lim[1], l2 <= lim[2] and l2 >= lim[3]. An inside
 * pixel whose (float) |o|^2 + 1 is below best[i] (0: no box yet) takes the box: best[i] = that,
 * flow[i] = (v0 - omega * q1, v1 + omega * q0, v2) with q = (R o)[0:2] (R's first two rows,
 * camera to world: o's world x, y), dynamic[i] = 1, confidence[i] = conf. Returns the number of
 * pixels that took the box. Double precision, the arithmetic of the numpy reference in its order. */
#include <stdint.h>

int64_t phigenesis_scene_flow_pixels(const float *depth, const double *rays, int64_t w, int64_t v0, int64_t v1,
                                     int64_t u0, int64_t u1, double z_near, double z_far, const double *c,
                                     const double *box, const double *lim, const double *rot_xy,
                                     const double *vel, double omega, float conf, float *best, float *flow,
                                     uint8_t *dynamic, float *confidence) {
    int64_t taken = 0;
    for (int64_t v = v0; v < v1; ++v) {
        for (int64_t u = u0; u < u1; ++u) {
            const int64_t i = v * w + u;
            const double d = (double)depth[i];
            if (!(d > z_near && d <= z_far)) continue;
            const double *r = rays + 3 * i;
            const double o0 = r[0] * d - c[0], o1 = r[1] * d - c[1], o2 = r[2] * d - c[2];
            const double l0 = o0 * box[0] + o1 * box[3] + o2 * box[6];
            const double l1 = o0 * box[1] + o1 * box[4] + o2 * box[7];
            const double l2 = o0 * box[2] + o1 * box[5] + o2 * box[8];
            if (!(l0 <= lim[0] && -l0 <= lim[0] && l1 <= lim[1] && -l1 <= lim[1] && l2 <= lim[2] && l2 >= lim[3]))
                continue;
            const float dist = (float)(o0 * o0 + o1 * o1 + o2 * o2 + 1.0);
            if (!(best[i] == 0.0f || dist < best[i])) continue;
            best[i] = dist;
            const double q0 = rot_xy[0] * o0 + rot_xy[1] * o1 + rot_xy[2] * o2;
            const double q1 = rot_xy[3] * o0 + rot_xy[4] * o1 + rot_xy[5] * o2;
            flow[3 * i] = (float)(vel[0] - omega * q1);
            flow[3 * i + 1] = (float)(vel[1] + omega * q0);
            flow[3 * i + 2] = (float)vel[2];
            dynamic[i] = 1;
            confidence[i] = conf;
            ++taken;
        }
    }
    return taken;
}
