/* The two readers of the matching-entropy estimator's sparse volume of window entropies
 * (recon/entropy/volume.py, SparseVolume), compiled ahead of time so that they run without numba:
 * each mirrors its numba twin operation for operation on the same types, so it gives the same bits.
 *
 * - lfrig_take: _take_kernel (SparseVolume.take), each pixel's entry at its index;
 * - lfrig_window_major: _window_major_kernel (SparseVolume.window_major), rows laid out (K, W),
 *   scaled, inf where not finite.
 *
 * Arrays are C-contiguous: mask (H, W, nb) uint8, a pixel's entries k = 0..K-1 packed as
 * numpy.packbits packs them (k = 0 the high bit of byte 0; nb = (K + 7) / 8); start (H * W + 1,)
 * int64, where each pixel's entries begin in values (float32, ascending k). Each output element is
 * computed by one thread alone, so the rows may go to the threads in any order. A pixel's entries
 * are found by its mask's set bits, counted a byte at a time (the rank of an entry is an integer,
 * the same however it is counted) and visited by the set bits only: the same entries in the same
 * order as the numba kernels' loops over every k.
 */
#include "rows.h"

/* What a call's rows read, and where they write. */
struct volume_args {
    const uint8_t *mask;
    int64_t nb;
    const int64_t *start;
    const float *values;
    const int64_t *index;
    int64_t a, W, K;
    float fill, scale;
    float *out;
};

/* One row y of _take_kernel: out[y, x] the entry of pixel (y, x) at k = index[y, x] (+ K where
 * negative) when bit k of its mask is set (the entry after the set bits below k), else fill. */
static int take_row(void *ctx, int64_t y) {
    const struct volume_args *v = ctx;
    const int64_t W = v->W, K = v->K, nb = v->nb;
    for (int64_t x = 0; x < W; x++) {
        const int64_t p = y * W + x;
        int64_t k = v->index[p];
        if (k < 0) k += K;
        const uint8_t *bits = v->mask + p * nb;
        const uint8_t byte = bits[k >> 3];
        if (!(byte & (0x80 >> (k & 7)))) {
            v->out[p] = v->fill;
            continue;
        }
        int64_t rank = __builtin_popcount((unsigned)byte >> (8 - (k & 7)));  /* the bits above k's in its byte */
        for (int64_t j = 0; j < (k >> 3); j++) rank += __builtin_popcount(bits[j]);
        v->out[p] = v->values[v->start[p] + rank];
    }
    return 0;
}

/* One row r of _window_major_kernel: the row's (K, W) filled with inf, then each entry of pixel
 * (a + r, x), ascending k, times scale (float32) written at (k, x) where finite. */
static int window_major_row(void *ctx, int64_t r) {
    const struct volume_args *v = ctx;
    const int64_t W = v->W, K = v->K, nb = v->nb;
    const float scale = v->scale;
    float *restrict dst = v->out + r * K * W;
    for (int64_t i = 0; i < K * W; i++) dst[i] = INFINITY;
    const int64_t y = v->a + r;
    for (int64_t x = 0; x < W; x++) {
        const int64_t p = y * W + x;
        const uint8_t *bits = v->mask + p * nb;
        const float *restrict values = v->values + v->start[p];
        int64_t i = 0;
        for (int64_t j = 0; j < nb && j * 8 < K; j++) {
            unsigned byte = bits[j];
            if (K - j * 8 < 8) byte &= 0xffu << (8 - (K - j * 8));  /* the bits of k < K only */
            while (byte) {
                const int lead = __builtin_clz(byte) - 24;  /* the highest set bit: the lowest k */
                byte &= ~(0x80u >> lead);
                const float s = values[i] * scale;
                i += 1;
                if (isfinite(s)) dst[(j * 8 + lead) * W + x] = s;
            }
        }
    }
    return 0;
}

/* _take_kernel: out (H, W) float32 from index (H, W) int64 in -K..K-1, rows dealt to `threads`
 * threads. */
int lfrig_take(const uint8_t *mask, int64_t nb, const int64_t *start, const float *values, const int64_t *index,
               int64_t H, int64_t W, int64_t K, float fill, float *out, int64_t threads) {
    if (H <= 0 || W <= 0) return 0;
    struct volume_args v = {mask, nb, start, values, index, 0, W, K, fill, 0.0f, out};
    return run_items(take_row, &v, H, threads);
}

/* _window_major_kernel: out (n, K, W) float32, rows a .. a + n - 1 of the volume, dealt to `threads`
 * threads. */
int lfrig_window_major(const uint8_t *mask, int64_t nb, const int64_t *start, const float *values, int64_t a,
                       int64_t n, int64_t W, int64_t K, float scale, float *out, int64_t threads) {
    if (n <= 0) return 0;
    struct volume_args v = {mask, nb, start, values, NULL, a, W, K, 0.0f, scale, out};
    return run_items(window_major_row, &v, n, threads);
}
