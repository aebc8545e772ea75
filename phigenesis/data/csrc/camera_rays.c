/* A camera's per-calibration tables (phigenesis/data/native.py): undistorted pixel rays, their
 * ego-frame unit directions, and the range view's overlap map.
 *
 * Each is one pass over the image's pixels computing what the numpy references compute
 * (camera_tables.undistorted_pixel_rays_reference, rangeview.camera_rays_ego_reference,
 * rangeview._overlap_reference). The ego rays and the overlap map use the same arithmetic in
 * the same order (the library is built with -std=c99, so no multiply-add contraction changes a
 * rounding) and equal the references; the undistortion solves the same equation by Newton's
 * method from a better start, to rounding level (the reference accepts OpenCV's points at a
 * residual of 1e-12). At 1920 x 1280 the references spend about 1.3, 0.8 and 0.3 CPU-s per
 * camera (OpenCV's fixed point; numpy's passes over (H * W, 3) float64 temporaries), the kernels
 * 0.03, 0.02 and 0.04. Also here: the ego body's depth (every box in one vectorised pass), the
 * ray components of camera_tables.RayComponents and the undistortion of arbitrary points.
 *
 * Distortion is OpenCV's five coefficients (k1, k2, p1, p2, k3), as in phigenesis/geometry.py.
 */
#include <math.h>
#include <stdint.h>

/* Floating-point traps are never enabled here, so GCC may evaluate both sides of a select (the
 * branchless loops vectorise only so); the values computed are the same. */
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC optimize("no-trapping-math")
#endif

/* The residual (normalised units) under which a pixel's solve has converged; one more Newton
 * step then leaves it at rounding level (camera_tables.UNDISTORT_TOLERANCE). */
#define CONVERGED 1e-12
/* geometry.undistort_normalized's iteration count (the reference for pixels that do not
 * converge: no undistorted point maps to them). */
#define REFERENCE_ITERATIONS 20
/* pi as numpy's np.pi (M_PI is not ISO C). */
#define PI 3.141592653589793

/* One Newton step of geometry.undistort_normalized at (*x, *y) towards (tx, ty): the same
 * expressions, evaluated in numpy's order, then the clamp to the monotonic radius r_max.
 * With exact = 0 the step divides once (by the determinant) instead of twice and skips the
 * clamp's square root well inside r_max: the same step to a few ulps, for the solves that go on
 * to convergence (the root does not depend on the path). Returns the residual max(|fx|, |fy|)
 * before the step; *jacobian is the determinant of the distortion's Jacobian there. */
static inline double newton_step(double *x_io, double *y_io, double tx, double ty, const double *d,
                                 double r_max, int exact, double *jacobian) {
    const double k1 = d[0], k2 = d[1], p1 = d[2], p2 = d[3], k3 = d[4];
    const double x = *x_io, y = *y_io;
    const double r2 = x * x + y * y;
    const double radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    const double dradial = k1 + r2 * (2 * k2 + 3 * k3 * r2);
    const double fx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - tx;
    const double fy = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - ty;
    const double j00 = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x;
    const double j01 = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y;
    const double j10 = j01;
    const double j11 = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x;
    double det = j00 * j11 - j01 * j10;
    *jacobian = det;
    if (fabs(det) < 1e-12) det = 1e-12;
    double nx, ny;
    if (exact) {
        nx = x - (j11 * fx - j01 * fy) / det;
        ny = y - (j00 * fy - j10 * fx) / det;
    } else {
        const double inverse = 1.0 / det;
        nx = x - (j11 * fx - j01 * fy) * inverse;
        ny = y - (j00 * fy - j10 * fx) * inverse;
    }
    const double s2 = nx * nx + ny * ny;
    if (exact || !(s2 < 0.98 * r_max * r_max)) {
        const double r = sqrt(s2);
        if (r > r_max) {
            const double s = r_max / (r > 1e-300 ? r : 1e-300);
            nx *= s;
            ny *= s;
        }
    }
    *x_io = nx;
    *y_io = ny;
    const double ax = fabs(fx), ay = fabs(fy);
    return ax > ay ? ax : ay; /* NaN compares false: a NaN residual never reads as converged */
}

/* Solves distort(x, y) = (tx, ty) from the start (*x, *y): Newton steps until the residual is
 * under CONVERGED, then one more. Returns 1 if it converged within max_steps on the image's own
 * sheet of the distortion (Jacobian determinant > 0: a distortion that is not one-to-one, its
 * tangential terms folding the image over near the monotonic radius, also maps points of the
 * fold-over sheet, where the determinant is negative, to some pixels), else 0 (the point is
 * then the last iterate). */
static int solve(double *x, double *y, double tx, double ty, const double *d, double r_max,
                 int max_steps) {
    double jacobian;
    for (int i = 0; i < max_steps; ++i) {
        if (newton_step(x, y, tx, ty, d, r_max, 0, &jacobian) <= CONVERGED) {
            if (!(jacobian > 0.0)) return 0;
            newton_step(x, y, tx, ty, d, r_max, 0, &jacobian);
            return 1;
        }
    }
    return 0;
}

/* geometry.undistort_normalized for one point: 20 steps from the distorted point (tx, ty), the
 * reference's arithmetic. Returns 1 if the result distorts back within CONVERGED. */
static int solve_as_reference(double *x, double *y, double tx, double ty, const double *d,
                              double r_max) {
    double jacobian, unused_x, unused_y;
    *x = tx;
    *y = ty;
    for (int i = 0; i < REFERENCE_ITERATIONS; ++i) newton_step(x, y, tx, ty, d, r_max, 1, &jacobian);
    unused_x = *x;
    unused_y = *y;
    return newton_step(&unused_x, &unused_y, tx, ty, d, r_max, 1, &jacobian) <= CONVERGED;
}

/* One Newton step without branches (so that a loop of them vectorises): newton_step's fast
 * form, clamping by a select. Returns the residual before the step in *residual and the
 * Jacobian's determinant there in *jacobian. */
static inline void branchless_step(double *x_io, double *y_io, double tx, double ty, const double *d,
                                   double r_max, double *residual, double *jacobian) {
    const double k1 = d[0], k2 = d[1], p1 = d[2], p2 = d[3], k3 = d[4];
    const double x = *x_io, y = *y_io;
    const double r2 = x * x + y * y;
    const double radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
    const double dradial = k1 + r2 * (2 * k2 + 3 * k3 * r2);
    const double fx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - tx;
    const double fy = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - ty;
    const double j00 = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x;
    const double j01 = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y;
    const double j11 = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x;
    const double det = j00 * j11 - j01 * j01;
    const double safe = fabs(det) < 1e-12 ? 1e-12 : det;
    const double inverse = 1.0 / safe;
    const double nx = x - (j11 * fx - j01 * fy) * inverse;
    const double ny = y - (j00 * fy - j01 * fx) * inverse;
    const double s2 = nx * nx + ny * ny;
    const double scale = s2 > r_max * r_max ? r_max / sqrt(s2) : 1.0;
    *x_io = nx * scale;
    *y_io = ny * scale;
    const double ax = fabs(fx), ay = fabs(fy);
    *residual = ax > ay ? ax : ay;
    *jacobian = det;
}

/* One image row below the second: every pixel starts from the line through the solutions of
 * the two rows above (x2, y2: two rows up, x1, y1: one row up; off by ~1e-7) and takes three
 * branchless Newton steps; ok[u] says whether the second step began within CONVERGED of a
 * solution on the image's own sheet (the third then reaches rounding level). The loop has no
 * branches and no dependency between pixels, so it runs four pixels a vector. */
static void solve_row(int64_t width, double ty, const double *k, const double *d, double r_max,
                      const double *restrict x2, const double *restrict y2,
                      const double *restrict x1, const double *restrict y1, double *restrict x0,
                      double *restrict y0, unsigned char *restrict ok) {
    for (int64_t u = 0; u < width; ++u) {
        const double tx = ((double)u - k[2] - k[1] * ty) / k[0];
        double x = 2.0 * x1[u] - x2[u], y = 2.0 * y1[u] - y2[u];
        double residual, jacobian;
        branchless_step(&x, &y, tx, ty, d, r_max, &residual, &jacobian);
        branchless_step(&x, &y, tx, ty, d, r_max, &residual, &jacobian);
        ok[u] = (residual <= CONVERGED) & (jacobian > 0.0);
        branchless_step(&x, &y, tx, ty, d, r_max, &residual, &jacobian);
        x0[u] = x;
        y0[u] = y;
    }
}

/* rays: (height * width, 3) float64 camera-frame rays (z = 1) of every pixel centre, row-major;
 * k: the 3 x 3 camera matrix (row-major), d: the five distortion coefficients, r_max:
 * geometry.max_monotonic_radius(d); scratch: 6 * width + width / 8 + 1 doubles. Each pixel is
 * solved by Newton's method from a prediction: in the first row its left neighbour's solution,
 * in the second the solution above it, below that the line through the two solutions above it
 * (solve_row: three steps, four pixels at a time). A pixel that does not converge so (within 8
 * steps in the first two rows), or converges on the fold-over sheet (see solve), is solved again
 * from its prediction by up to 8 plain steps, then as geometry.undistort_normalized does (20
 * steps from the distorted point, clamped to r_max), so it gets the reference's result. Returns
 * how many pixels that leaves further than CONVERGED from a solution (no undistorted point maps
 * to them). */
int64_t phigenesis_undistort_grid(int64_t width, int64_t height, const double *k, const double *d,
                                  double r_max, double *rays, double *scratch) {
    int64_t unsolved = 0;
    /* The solutions of the last three rows, x and y apart (this row, one up, two up). */
    double *xs[3] = {scratch, scratch + width, scratch + 2 * width};
    double *ys[3] = {scratch + 3 * width, scratch + 4 * width, scratch + 5 * width};
    unsigned char *ok = (unsigned char *)(scratch + 6 * width);
    for (int64_t v = 0; v < height; ++v) {
        const double ty = ((double)v - k[5]) / k[4];
        double *x0 = xs[v % 3], *y0 = ys[v % 3];
        const double *x1 = xs[(v + 2) % 3], *y1 = ys[(v + 2) % 3];
        const double *x2 = xs[(v + 1) % 3], *y2 = ys[(v + 1) % 3];
        if (v >= 2) solve_row(width, ty, k, d, r_max, x2, y2, x1, y1, x0, y0, ok);
        for (int64_t u = 0; u < width; ++u) {
            if (v >= 2 && ok[u]) continue;
            const double tx = ((double)u - k[2] - k[1] * ty) / k[0];
            double x = tx, y = ty;
            if (v >= 2) {
                x = 2.0 * x1[u] - x2[u];
                y = 2.0 * y1[u] - y2[u];
            } else if (v == 1) {
                x = x1[u];
                y = y1[u];
            } else if (u > 0) {
                x = x0[u - 1];
                y = y0[u - 1];
            }
            if (!isfinite(x) || !isfinite(y)) {
                x = tx;
                y = ty;
            }
            if (!solve(&x, &y, tx, ty, d, r_max, 8) && !solve_as_reference(&x, &y, tx, ty, d, r_max))
                ++unsolved;
            x0[u] = x;
            y0[u] = y;
        }
        double *row = rays + 3 * v * width;
        for (int64_t u = 0; u < width; ++u) {
            row[3 * u] = x0[u];
            row[3 * u + 1] = y0[u];
            row[3 * u + 2] = 1.0;
        }
    }
    return unsolved;
}

/* points: (n, 2) float64 distorted normalised coordinates; out: (n, 2) their undistorted points
 * (geometry.undistort_normalized), each solved from itself by up to 8 Newton steps on the
 * image's own sheet (see solve), else as the reference (20 steps, clamped to r_max). Returns
 * how many are left further than CONVERGED from a solution. */
int64_t phigenesis_undistort_points(const double *points, int64_t n, const double *d, double r_max,
                                    double *out) {
    int64_t unsolved = 0;
    for (int64_t p = 0; p < n; ++p) {
        const double tx = points[2 * p], ty = points[2 * p + 1];
        double x = tx, y = ty;
        if (!solve(&x, &y, tx, ty, d, r_max, 8) && !solve_as_reference(&x, &y, tx, ty, d, r_max))
            ++unsolved;
        out[2 * p] = x;
        out[2 * p + 1] = y;
    }
    return unsolved;
}

/* A camera's ray components (camera_tables.ray_components_from_rays): from the (height * width, 3)
 * float64 rays (z = 1), the float32 planes x, y and norm = sqrt(x^2 + y^2 + 1) (height, width),
 * each column's least and greatest x (column_x: (2, width) float64) and each row's least and
 * greatest y (row_y: (2, height)), NaN where a NaN ray is (as numpy's min and max). */
void phigenesis_ray_components(const double *rays, int64_t width, int64_t height, float *x_out,
                               float *y_out, float *norm_out, double *column_x, double *row_y) {
    for (int64_t u = 0; u < width; ++u) {
        column_x[u] = INFINITY;
        column_x[width + u] = -INFINITY;
    }
    for (int64_t v = 0; v < height; ++v) {
        double y_min = INFINITY, y_max = -INFINITY;
        for (int64_t u = 0; u < width; ++u) {
            const int64_t p = v * width + u;
            const double x = rays[3 * p], y = rays[3 * p + 1];
            x_out[p] = (float)x;
            y_out[p] = (float)y;
            norm_out[p] = (float)sqrt(x * x + y * y + 1.0);
            /* a NaN, once met, stays: nothing compares below or above it */
            y_min = (y < y_min) | (y != y) ? y : y_min;
            y_max = (y > y_max) | (y != y) ? y : y_max;
            column_x[u] = (x < column_x[u]) | (x != x) ? x : column_x[u];
            column_x[width + u] = (x > column_x[width + u]) | (x != x) ? x : column_x[width + u];
        }
        row_y[v] = y_min;
        row_y[height + v] = y_max;
    }
}

/* out: (n, 3) float32 unit directions, ego axes, of the (n, 3) float64 camera-frame rays:
 * rotated by ego_from_camera's rotation r (3 x 3, row-major), divided by their length,
 * rounded to float32. */
/* One ray's unit direction in ego axes (r: ego_from_camera's rotation, row-major), each
 * component divided by the length and rounded to float32. */
static inline void ray_ego(const double *a, const double *r, float *out) {
    double e[3];
    for (int i = 0; i < 3; ++i) e[i] = a[0] * r[3 * i] + a[1] * r[3 * i + 1] + a[2] * r[3 * i + 2];
    const double norm = sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2]);
    for (int i = 0; i < 3; ++i) out[i] = (float)(e[i] / norm);
}

void phigenesis_rays_ego(const double *rays, int64_t n, const double *r, float *out) {
    for (int64_t p = 0; p < n; ++p) ray_ego(rays + 3 * p, r, out + 3 * p);
}

/* geometry.wrap_angle: to [-pi, pi). */
static double wrap_angle(double a) {
    const double two_pi = 2.0 * PI;
    double w = fmod(a + PI, two_pi);
    if (w < 0) w += two_pi;
    w -= PI;
    return w >= PI ? w - two_pi : w;
}

/* Whether a ray's azimuth is within a view's azimuth range (rangeview._overlap_reference's
 * pre-test, |wrap_angle(atan2(y, x) - middle)| <= half), decided without atan2: for half in
 * [0, pi] it holds when cos(azimuth - middle) >= cos(half), i.e. when
 * f = x cos(middle) + y sin(middle) - |(x, y)| cos(half) >= 0. |f| / |(x, y)| is at most the
 * angle to the range's edge, so where it exceeds 1e-9 the sign decides as atan2 would; within
 * 1e-9, at a pole (x = y = 0), for half > pi or NaN the reference's own arithmetic does. */
typedef struct {
    double middle, half, cos_middle, sin_middle, cos_half;
} AzimuthRange;

static int in_azimuth_range(double x, double y, const AzimuthRange *range) {
    const double h = sqrt(x * x + y * y);
    if (h > 0.0 && h < INFINITY && range->half <= PI) {
        const double f = x * range->cos_middle + y * range->sin_middle - h * range->cos_half;
        if (f > 1e-9 * h) return 1;
        if (f < -1e-9 * h) return 0;
    }
    return fabs(wrap_angle(atan2(y, x) - range->middle)) <= range->half;
}

/* Ray (ego axes) into view j's camera axes, rounded as rangeview.to_camera rounds it. */
static void to_camera(const double *dir, const double *r, double *c) {
    for (int i = 0; i < 3; ++i) c[i] = dir[0] * r[i] + dir[1] * r[3 + i] + dir[2] * r[6 + i];
}

/* 1 if the camera-frame direction c lands inside view j's image (geometry.project_points with
 * its default minimum depth, then geometry.in_image). */
static int in_view(const double *c, const double *k, const double *d, double r_max2, int64_t width,
                   int64_t height) {
    if (!(isfinite(c[0]) && isfinite(c[1]) && isfinite(c[2]) && c[2] > 1e-6)) return 0;
    double x = c[0] / c[2], y = c[1] / c[2];
    if (isfinite(r_max2)) { /* the distortion model is applied (some coefficient is not 0) */
        const double r2 = x * x + y * y;
        if (!(r2 <= r_max2)) return 0;
        const double radial = 1.0 + r2 * (d[0] + r2 * (d[1] + r2 * d[4]));
        const double xd = x * radial + 2 * d[2] * x * y + d[3] * (r2 + 2 * x * x);
        const double yd = y * radial + d[2] * (r2 + 2 * y * y) + 2 * d[3] * x * y;
        x = xd;
        y = yd;
    }
    const double u = k[0] * x + k[1] * y + k[2];
    const double v = k[4] * y + k[5];
    return u >= -0.5 && u < (double)width - 0.5 && v >= -0.5 && v < (double)height - 0.5;
}

/* One ray's owner and coverage (see phigenesis_overlap); dir: its unit direction in ego axes,
 * float32 values held as float64. */
static void overlap_one(const double *dir, int64_t k, int64_t views, const double *rotation,
                        const double *intrinsics, const double *distortion, const double *r_max2,
                        const int64_t *size, const AzimuthRange *ranges, uint8_t *owner,
                        uint8_t *count) {
    double own[3];
    to_camera(dir, rotation + 9 * k, own);
    double best = own[2];
    int64_t best_view = k;
    int seen = 1;
    for (int64_t j = 0; j < views; ++j) {
        if (j == k || !in_azimuth_range(dir[0], dir[1], &ranges[j])) continue;
        double c[3];
        to_camera(dir, rotation + 9 * j, c);
        if (!in_view(c, intrinsics + 9 * j, distortion + 5 * j, r_max2[j], size[2 * j],
                     size[2 * j + 1]))
            continue;
        ++seen;
        if (c[2] > best || (c[2] == best && j < best_view)) {
            best = c[2];
            best_view = j;
        }
    }
    *owner = (uint8_t)best_view;
    *count = (uint8_t)seen;
}

/* The views' azimuth ranges (azimuth: (views, 2) middle and half-width) for in_azimuth_range. */
static void azimuth_ranges(const double *azimuth, int64_t views, AzimuthRange *ranges) {
    for (int64_t j = 0; j < views && j < 256; ++j) {
        const double middle = azimuth[2 * j], half = azimuth[2 * j + 1];
        ranges[j] = (AzimuthRange){middle, half, cos(middle), sin(middle), cos(half)};
    }
}

/* The overlap map of view k's n rays (rays: (n, 3) float32 unit directions, ego axes):
 * owner[p] is the view whose optical axis is nearest in angle among the views whose image holds
 * the direction (ties to the lower index; view k always holds its own), count[p] how many do.
 * Only views whose azimuth span (with its slack) holds the ray's azimuth are tested; views <= 255
 * (uint8 owners, 255 = no view). */
void phigenesis_overlap(const float *rays, int64_t n, int64_t k, int64_t views,
                        const double *rotation, const double *intrinsics, const double *distortion,
                        const double *r_max2, const int64_t *size, const double *azimuth,
                        uint8_t *owner, uint8_t *count) {
    AzimuthRange ranges[256];
    azimuth_ranges(azimuth, views, ranges);
    for (int64_t p = 0; p < n; ++p) {
        const double dir[3] = {rays[3 * p], rays[3 * p + 1], rays[3 * p + 2]};
        overlap_one(dir, k, views, rotation, intrinsics, distortion, r_max2, size, ranges, owner + p,
                    count + p);
    }
}

/* phigenesis_overlap of view k's camera-frame rays ((n, 3) float64, z = 1), turned into float32
 * unit directions in ego axes (phigenesis_rays_ego) a block at a time: the same map without an
 * (n, 3) float32 array of directions. (Making each direction inside the overlap's loop instead
 * was slower, and GCC 12's SLP vectoriser at -O2 and above dropped the float32 rounding of two
 * of its three components there: one pixel of the real Waymo rig changed owner.) */
void phigenesis_overlap_camera_rays(const double *rays, int64_t n, int64_t k, int64_t views,
                                    const double *rotation, const double *intrinsics,
                                    const double *distortion, const double *r_max2,
                                    const int64_t *size, const double *azimuth, uint8_t *owner,
                                    uint8_t *count) {
    enum { BLOCK = 2048 };
    float directions[3 * BLOCK];
    for (int64_t p0 = 0; p0 < n; p0 += BLOCK) {
        const int64_t m = n - p0 < BLOCK ? n - p0 : BLOCK;
        phigenesis_rays_ego(rays + 3 * p0, m, rotation + 9 * k, directions);
        phigenesis_overlap(directions, m, k, views, rotation, intrinsics, distortion, r_max2, size,
                           azimuth, owner + p0, count + p0);
    }
}

/* np.minimum / np.maximum of two doubles: NaN if either is (branchless). */
static inline double nan_min(double a, double b) { return ((a != a) | (b != b)) ? a + b : (a < b ? a : b); }
static inline double nan_max(double a, double b) { return ((a != a) | (b != b)) ? a + b : (a > b ? a : b); }
/* np.fmax / np.fmin: a NaN operand is skipped (branchless). */
static inline double skip_max(double a, double b) { return a != a ? b : (b != b ? a : (a > b ? a : b)); }
static inline double skip_min(double a, double b) { return a != a ? b : (b != b ? a : (a < b ? a : b)); }

/* One box over rays [p0, p1): near[p] = min(near[p], entry depth rounded to float32) where the
 * ray enters the box (the slab test of camera_tables.ray_box_depths, its arithmetic). */
static void box_near_span(const double *restrict rays, int64_t p0, int64_t p1,
                          const double *restrict m, const double *restrict half,
                          float *restrict near) {
    const double m00 = m[0], m01 = m[1], m02 = m[2], o0 = m[3];
    const double m10 = m[4], m11 = m[5], m12 = m[6], o1 = m[7];
    const double m20 = m[8], m21 = m[9], m22 = m[10], o2 = m[11];
    const double h0 = half[0], h1 = half[1], h2 = half[2];
    for (int64_t p = p0; p < p1; ++p) {
        const double rx = rays[3 * p], ry = rays[3 * p + 1], rz = rays[3 * p + 2];
        const double d0 = m00 * rx + m01 * ry + m02 * rz;
        const double d1 = m10 * rx + m11 * ry + m12 * rz;
        const double d2 = m20 * rx + m21 * ry + m22 * rz;
        const double a0 = (-h0 - o0) / d0, b0 = (h0 - o0) / d0;
        const double a1 = (-h1 - o1) / d1, b1 = (h1 - o1) / d1;
        const double a2 = (-h2 - o2) / d2, b2 = (h2 - o2) / d2;
        /* t_near = fmax(fmax(lo0, lo1), lo2), t_far likewise, as ray_box_depths computes them. */
        const double t_near = skip_max(skip_max(nan_min(a0, b0), nan_min(a1, b1)), nan_min(a2, b2));
        const double t_far = skip_min(skip_min(nan_max(a0, b0), nan_max(a1, b1)), nan_max(a2, b2));
        const double start = t_near > 0.0 ? t_near : 0.0;
        const int hit = (fabs(t_near) < INFINITY) & (fabs(t_far) < INFINITY) & (t_far >= start);
        const float entry = hit ? (float)start : INFINITY;
        near[p] = entry < near[p] ? entry : near[p];
    }
}

/* The ego body's depth (camera_tables.ego_body_depth_from_rays): rays (n, 3) float64 camera-frame
 * rays (z = 1); boxes box_from_camera (boxes, 3, 4) row-major and half sizes (boxes, 3). near[p]
 * becomes the least depth at which ray p enters a box (0 from inside), rounded to float32, where
 * it enters one; it is left as is elsewhere. ray_box.c's phigenesis_ray_box_near per box, written
 * without branches so that it runs several rays a vector, over blocks of rays that stay in
 * cache while every box is tested. */
void phigenesis_ray_boxes_near(const double *restrict rays, int64_t n, int64_t boxes,
                               const double *restrict box_from_camera, const double *restrict half,
                               float *restrict near) {
    const int64_t block = 2048;
    for (int64_t p0 = 0; p0 < n; p0 += block) {
        const int64_t p1 = p0 + block < n ? p0 + block : n;
        for (int64_t b = 0; b < boxes; ++b)
            box_near_span(rays, p0, p1, box_from_camera + 12 * b, half + 3 * b, near);
    }
}
