/* Range-image returns to points: the inner loop of the Waymo reader (phigenesis/data/native.py).
 *
 * A range image is float32 (H, W, C), channel 0 the range in metres, 1 the intensity, 2 the
 * elongation. A pixel is a return when its range is positive, NaN or +-inf (a non-finite range is
 * kept so that the sweep drops and counts it; 0 and negatives mean no return). The rays are
 * factored per row and column (see convert._RayGeometry): the direction of pixel (h, w) is
 * cos_incl[h] * along[:, w] + sin_incl[h] * up[:, w], its origin origin[:, w], both (3, W) arrays.
 * Plain C, no Python or torch headers: built with the system compiler in about a second and
 * loaded with ctypes.
 */
#include <math.h>
#include <stdint.h>

static inline int is_return(float r) { return !(r <= 0.0f) || r == -INFINITY; }

/* Writes the returns, row by row (the order of numpy's flatnonzero), into the outputs from
 * index 0. Returns the number written, or -1 when the image holds more than `capacity` returns
 * (H * W is always enough). points and origins are (N, 3) C order;
 * intensity, elongation (N,); beam (N,) the row; time_offset (N,) time_offsets[column]. */
int64_t phigenesis_gather_returns(const float *image, int64_t h, int64_t w, int64_t c,
                                  const float *cos_incl, const float *sin_incl, const float *along,
                                  const float *up, const float *origin, const int32_t *time_offsets,
                                  float *points, float *origins, float *intensity, float *elongation,
                                  uint16_t *beam, int32_t *time_offset, int64_t capacity) {
    int64_t n = 0;
    for (int64_t row = 0; row < h; ++row) {
        const float ci = cos_incl[row], si = sin_incl[row];
        const float *pixel = image + row * w * c;
        for (int64_t col = 0; col < w; ++col, pixel += c) {
            const float r = pixel[0];
            if (!is_return(r)) continue;
            if (n >= capacity) return -1;
            for (int k = 0; k < 3; ++k) {
                const float o = origin[k * w + col];
                points[3 * n + k] = (along[k * w + col] * ci + up[k * w + col] * si) * r + o;
                origins[3 * n + k] = o;
            }
            intensity[n] = c > 1 ? pixel[1] : 0.0f;
            elongation[n] = c > 2 ? pixel[2] : 0.0f;
            beam[n] = (uint16_t)row;
            time_offset[n] = time_offsets[col];
            ++n;
        }
    }
    return n;
}
