/* The view filters' per-pixel steps of the matching-entropy estimator (recon/entropy/noise.py),
 * compiled ahead of time: each mirrors its numpy/OpenCV twin operation for operation on the same
 * types (no fused multiply-add), so it gives the same bits.
 *
 * - lfrig_warp_mask: warp_mask_to_views' forward warp of a centre-view mask into views, each
 *   landing grown by one pixel (the twin's cv2.dilate with a 3x3 square), a view an item;
 * - lfrig_blend: _blend_filtered's join, view + weight * (filtered - view) in float32 (the twin's
 *   cv2.subtract, cv2.multiply and cv2.add).
 *
 * Arrays are C-contiguous. The Gaussian blurs stay OpenCV's: their rounding is OpenCV's own.
 */
#include "rows.h"

/* What a call's views read, and where they write. */
struct warp_args {
    const int64_t *ys, *xs;
    const double *d;
    int64_t n;
    const int64_t *du, *dv;
    int64_t a, b, top, bottom, W;
    uint8_t *out;
};

/* One view k: its plane of out ((bottom - top, W) uint8) set to 1 within one pixel of where the
 * mask's pixels i (ys, xs, d) land, floor(y - du d + 0.5), floor(x - dv d + 0.5), in double as
 * numpy computes them, when the landing lies in rows [a, b) and columns [0, W) (a landing outside
 * is dropped, NaN's among them; the comparisons are of whole doubles, as exact as the twin's of
 * int64 conversions); 0 elsewhere. Setting the 3x3 square of each landing gives the bits of
 * dilating the landings: an OR, in any order. */
static int warp_view(void *ctx, int64_t k) {
    const struct warp_args *w = ctx;
    const int64_t W = w->W, top = w->top, bottom = w->bottom;
    uint8_t *plane = w->out + k * (bottom - top) * W;
    memset(plane, 0, (size_t)((bottom - top) * W));
    const double du = (double)w->du[k], dv = (double)w->dv[k];
    const double a = (double)w->a, b = (double)w->b, right = (double)W;
    for (int64_t i = 0; i < w->n; i++) {
        const double fy = floor(((double)w->ys[i] - du * w->d[i]) + 0.5);
        if (!(fy >= a && fy < b)) continue;
        const double fx = floor(((double)w->xs[i] - dv * w->d[i]) + 0.5);
        if (!(fx >= 0.0 && fx < right)) continue;
        const int64_t ly = (int64_t)fy, lx = (int64_t)fx;
        const int64_t y0 = max64(ly - 1, top), y1 = min64(ly + 2, bottom);
        const int64_t x0 = max64(lx - 1, 0), x1 = min64(lx + 2, W);
        for (int64_t y = y0; y < y1; y++)
            for (int64_t x = x0; x < x1; x++) plane[(y - top) * W + x] = 1;
    }
    return 0;
}

/* warp_mask_to_views: out (n_views, bottom - top, W) uint8, view k shifted by (du[k], dv[k]) grid
 * steps from the centre; the mask's n pixels (ys, xs) int64 with their disparity d (double). */
int lfrig_warp_mask(const int64_t *ys, const int64_t *xs, const double *d, int64_t n, const int64_t *du,
                    const int64_t *dv, int64_t n_views, int64_t a, int64_t b, int64_t top, int64_t bottom,
                    int64_t W, uint8_t *out, int64_t threads) {
    struct warp_args w = {ys, xs, d, n, du, dv, a, b, top, bottom, W, out};
    return run_items(warp_view, &w, n_views, threads);
}

/* _blend_filtered's join of n values: out = view + weight * (filtered - view), each a float32
 * operation rounded on its own, in the twin's order. */
int lfrig_blend(const float *view, const float *weight, const float *filtered, int64_t n, float *out) {
    for (int64_t i = 0; i < n; i++) out[i] = view[i] + weight[i] * (filtered[i] - view[i]);
    return 0;
}
