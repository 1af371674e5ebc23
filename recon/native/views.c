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
 * int64 conversions); 0 elsewhere. The landings are marked in a scratch of rows [a, b), a zero
 * column on either side, and grown as the twin's cv2.dilate with a 3x3 square grows them (an OR
 * over the rows of [a, b) and the columns of [0, W) within a pixel), a row at a time: the OR of
 * the three rows around it, then of the three columns around each pixel (loops the compiler
 * vectorises, instead of three stores a row for every landing). */
static int warp_view(void *ctx, int64_t k) {
    const struct warp_args *w = ctx;
    const int64_t W = w->W, a = w->a, b = w->b, top = w->top, bottom = w->bottom, P = W + 2;
    uint8_t *restrict plane = w->out + k * (bottom - top) * W;
    uint8_t *restrict landed = calloc((size_t)((b - a) * P + P), 1); /* and a row for the OR of three */
    if (!landed) return 1;
    uint8_t *restrict across = landed + (b - a) * P;
    const double du = (double)w->du[k], dv = (double)w->dv[k];
    const double fa = (double)a, fb = (double)b, right = (double)W;
    for (int64_t i = 0; i < w->n; i++) {
        const double fy = floor(((double)w->ys[i] - du * w->d[i]) + 0.5);
        const double fx = floor(((double)w->xs[i] - dv * w->d[i]) + 0.5);
        if (fy >= fa && fy < fb && fx >= 0.0 && fx < right)
            landed[((int64_t)fy - a) * P + (int64_t)fx + 1] = 1;
    }
    for (int64_t y = top; y < bottom; y++) {
        const uint8_t *restrict r0 = landed + (max64(y - 1, a) - a) * P;
        const uint8_t *restrict r1 = landed + (y - a) * P;
        const uint8_t *restrict r2 = landed + (min64(y + 1, b - 1) - a) * P;
        for (int64_t x = 0; x < P; x++) across[x] = r0[x] | r1[x] | r2[x];
        uint8_t *restrict o = plane + (y - top) * W;
        for (int64_t x = 0; x < W; x++) o[x] = across[x] | across[x + 1] | across[x + 2];
    }
    free(landed);
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
