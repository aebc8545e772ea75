/* The depth projection's per-pixel plane fits (phigenesis/data/stages/project.py, fit_pixels) on
 * the occupied pixels of an h x w image, in a few passes over the n visible points instead of
 * numpy's sort and forty array passes.
 *
 * Point i lies in pixel pixel[i] at (u, v) = uv[2 i ..] with depth z[i] (float32, metres); du,
 * dv are its offsets from the pixel centre and y = 1 / z. For each occupied pixel (ascending flat
 * index, written to occupied[]): the moments n, du, dv, du^2, dv^2, du dv, y, du y, dv y, y^2
 * summed in the points' order; the least-squares plane y = a + b du + c dv (plane_fit below: a
 * is NaN with fewer than min_points points or points not spread in both directions); the depth at
 * the centre 1 / a clipped to the pixel's depth range widened by its span (and at least half its
 * nearest depth), NaN where a <= 0; mixed if a point lies farther than fit_tol_m + fit_tol_rel *
 * base from the plane (or, with no plane, from reference[pixel], the point nearest the centre).
 * With radius > 0, the plane of the (2 r + 1)^2 window's moments (each neighbour's shifted by its
 * offset, added in the numpy reference's order: dy, then dx) replaces the depth where its RMS
 * residual is within win_tol_m + win_tol_rel * z and it agrees with the base within the
 * tolerance. Every step is the numpy reference's arithmetic in its order (numpy's nan_to_num and
 * maximum semantics included), so the results are the same doubles.
 *
 * Outputs (capacity min(n, h w)): occupied (int64), depth (double), count (int64), mixed (uint8).
 * Returns the number of occupied pixels, or -1 if memory ran out. */
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

#define NM 10

/* numpy's _plane_at_centre for one pixel's moments m: a (NaN if no fit), b, c, rms. */
static void plane_fit(const double *m, int64_t min_points, double *a, double *b, double *c, double *rms) {
    const double n = m[0];
    const double mu = m[1] / n, mv = m[2] / n, my = m[6] / n;
    const double cuu = m[3] / n - mu * mu;
    const double cvv = m[4] / n - mv * mv;
    const double cuv = m[5] / n - mu * mv;
    const double cuy = m[7] / n - mu * my;
    const double cvy = m[8] / n - mv * my;
    const double cyy = m[9] / n - my * my;
    const double det = cuu * cvv - cuv * cuv;
    const int ok = (n >= (double)min_points) && (det > 1.6e-5);
    *b = ok ? (cvv * cuy - cuv * cvy) / det : 0.0;
    *c = ok ? (cuu * cvy - cuv * cuy) / det : 0.0;
    *a = ok ? my - *b * mu - *c * mv : NAN;
    const double r = cyy - *b * cuy - *c * cvy;
    *rms = sqrt(isnan(r) ? r : (r > 0.0 ? r : 0.0));
}

int64_t phigenesis_plane_fits(int64_t n, const int64_t *pixel, const double *uv, const float *z, int64_t h,
                              int64_t w, const float *reference, int64_t min_points, double fit_tol_m,
                              double fit_tol_rel, int64_t radius, double win_tol_m, double win_tol_rel,
                              int64_t *occupied, double *depth, int64_t *count, uint8_t *mixed) {
    int32_t *map = (int32_t *)calloc((size_t)(h * w), sizeof(int32_t));
    if (map == NULL) return -1;
    for (int64_t i = 0; i < n; ++i) map[pixel[i]] = 1;
    int64_t k = 0;
    for (int64_t p = 0; p < h * w; ++p) {
        if (map[p]) {
            occupied[k] = p;
            map[p] = (int32_t)(++k);
        }
    }
    double *own = (double *)calloc((size_t)(k * NM), sizeof(double));
    double *zr = (double *)malloc((size_t)(k * 6) * sizeof(double)); /* zmin, zmax, a, b, c, worst */
    if (own == NULL || zr == NULL) {
        free(map), free(own), free(zr);
        return -1;
    }
    for (int64_t j = 0; j < k; ++j) {
        zr[6 * j] = INFINITY;
        zr[6 * j + 1] = 0.0;
        zr[6 * j + 5] = 0.0;
    }
    for (int64_t i = 0; i < n; ++i) {
        const int64_t j = map[pixel[i]] - 1;
        const double du = uv[2 * i] - (double)(pixel[i] % w);
        const double dv = uv[2 * i + 1] - (double)(pixel[i] / w);
        const double zi = (double)z[i], y = 1.0 / zi;
        double *m = own + NM * j;
        m[0] += 1.0;
        m[1] += du;
        m[2] += dv;
        m[3] += du * du;
        m[4] += dv * dv;
        m[5] += du * dv;
        m[6] += y;
        m[7] += du * y;
        m[8] += dv * y;
        m[9] += y * y;
        if (zi < zr[6 * j]) zr[6 * j] = zi;
        if (zi > zr[6 * j + 1]) zr[6 * j + 1] = zi;
    }
    for (int64_t j = 0; j < k; ++j) {
        double a, b, c, rms;
        plane_fit(own + NM * j, min_points, &a, &b, &c, &rms);
        zr[6 * j + 2] = a, zr[6 * j + 3] = b, zr[6 * j + 4] = c;
        count[j] = (int64_t)own[NM * j];
        const double zmin = zr[6 * j], zmax = zr[6 * j + 1], span = zmax - zmin;
        if (a > 0) {
            double lo = zmin - span, half = 0.5 * zmin, x = 1.0 / a;
            lo = lo > half ? lo : half;
            x = x > lo ? x : lo;
            depth[j] = x < zmax + span ? x : zmax + span;
        } else {
            depth[j] = NAN;
        }
    }
    for (int64_t i = 0; i < n; ++i) {
        const int64_t j = map[pixel[i]] - 1;
        const double du = uv[2 * i] - (double)(pixel[i] % w);
        const double dv = uv[2 * i + 1] - (double)(pixel[i] / w);
        const double a = zr[6 * j + 2];
        const double expected =
            isfinite(a) ? 1.0 / (a + zr[6 * j + 3] * du + zr[6 * j + 4] * dv) : (double)reference[pixel[i]];
        double dev = fabs((double)z[i] - expected);
        if (isnan(dev)) dev = INFINITY;
        else if (isinf(dev)) dev = DBL_MAX;
        if (dev > zr[6 * j + 5]) zr[6 * j + 5] = dev;
    }
    for (int64_t j = 0; j < k; ++j) {
        const double ref = (double)reference[occupied[j]];
        const double base = isfinite(depth[j]) ? depth[j] : ref;
        const double tolerance = fit_tol_m + fit_tol_rel * base;
        mixed[j] = zr[6 * j + 5] > tolerance;
        if (radius <= 0) continue;
        const int64_t row = occupied[j] / w, col = occupied[j] % w;
        double s[NM] = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
        for (int64_t dy = -radius; dy <= radius; ++dy) {
            const int64_t r = row + dy;
            if (r < 0 || r >= h) continue;
            for (int64_t dx = -radius; dx <= radius; ++dx) {
                const int64_t cc = col + dx;
                if (cc < 0 || cc >= w) continue;
                const int32_t q = map[r * w + cc];
                if (q == 0) continue;
                const double *m = own + NM * (int64_t)(q - 1);
                const double nn = m[0], u = m[1], v = m[2], y = m[6];
                const double fx = (double)dx, fy = (double)dy;
                s[0] += nn;
                s[1] += m[1] + fx * nn;
                s[2] += m[2] + fy * nn;
                s[3] += m[3] + (double)(2 * dx) * u + (double)(dx * dx) * nn;
                s[4] += m[4] + (double)(2 * dy) * v + (double)(dy * dy) * nn;
                s[5] += m[5] + fx * v + fy * u + (double)(dx * dy) * nn;
                s[6] += y;
                s[7] += m[7] + fx * y;
                s[8] += m[8] + fy * y;
                s[9] += m[9];
            }
        }
        double wa, wb, wc, rms;
        plane_fit(s, min_points, &wa, &wb, &wc, &rms);
        const double wz = 1.0 / wa;
        const double wtol = win_tol_m + win_tol_rel * wz;
        const int good = isfinite(wz) && wz > 0 && rms * (wz * wz) <= wtol && fabs(wz - base) <= tolerance;
        if (good) depth[j] = wz;
    }
    free(map), free(own), free(zr);
    return k;
}
