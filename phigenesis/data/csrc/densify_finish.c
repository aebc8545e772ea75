/* The densifier's last pass over an image (phigenesis/data/stages/densify.py, _finish): the
 * support mask applied to the dense depth, the confidence of every output pixel and the clean-up
 * of _check_result, in one pass instead of numpy's dozen full-image temporaries.
 *
 * Pixel i (of n): d = dense[i] where support[i] and dense[i] > 0, else 0 (then depth and
 * confidence are 0). Measured pixels (sparse[i] > 0 and conf[i] > 0) refer to themselves, others
 * to their nearest trusted pixel j = lut[labels[i]] (labels: OpenCV's distance transform labels);
 * z_ref = sparse[.], c = conf[.], e = 0 when measured, else dist[i] * neg_inv_d0; then
 * rel = |d - z_ref| / (d * rel0) and confidence = c * exp(e - rel^2), clipped to [0, 1] (NaN: 0).
 * float32 in the order of depth_confidence (ISO C: no fused multiply-add), so the results equal
 * numpy's up to the last bit of exp. */
#include <math.h>
#include <stdint.h>

void phigenesis_densify_finish(int64_t n, const float *dense, const uint8_t *support, const float *sparse,
                               const float *conf, const int32_t *labels, const int32_t *lut, const float *dist,
                               float neg_inv_d0, float rel0, float *depth_out, float *conf_out) {
    for (int64_t i = 0; i < n; ++i) {
        const float d = dense[i];
        if (!support[i] || !(d > 0.0f) || !isfinite(d)) {
            depth_out[i] = 0.0f;
            conf_out[i] = 0.0f;
            continue;
        }
        float z_ref, c, e;
        if (sparse[i] > 0.0f && conf[i] > 0.0f) {
            z_ref = sparse[i];
            c = conf[i];
            e = 0.0f;
        } else {
            const int32_t j = lut[labels[i]];
            z_ref = sparse[j];
            c = conf[j];
            e = dist[i] * neg_inv_d0;
        }
        const float rel = fabsf(d - z_ref) / (d * rel0);
        float out = c * expf(e - rel * rel);
        if (!(out > 0.0f)) out = 0.0f; /* NaN too */
        if (out > 1.0f) out = 1.0f;
        depth_out[i] = d;
        conf_out[i] = out;
    }
}
