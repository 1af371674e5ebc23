/* The median filter with nearest borders (recon/entropy/median.py, median_filter_nearest), compiled
 * ahead of time so that it runs without numba: it mirrors its numba twin operation for operation on
 * the same types, so it gives the same bits.
 *
 * - lfrig_median: _median_kernel, on float32 (wide 0) or float64 (wide 1) images.
 *
 * Arrays are C-contiguous. Row by row, MEDIAN_COLUMNS columns at a time, each column's n samples
 * are gathered into the rows of a buffer (copied, bits and all), the selection network's
 * compare-exchanges run along them as in numba (u < v ? u : v the smaller, u < v ? v : u the larger:
 * NaN and -0.0, which that would order unlike scipy, never reach the kernel), and the sample of rank
 * `rank` is copied out. Each output pixel is computed by one thread alone, so the rows may go to the
 * threads in any order, and the block of columns changes no value. The row function takes `wide` as
 * a constant in each of its two callers, so that each has its own loads and compare-exchanges.
 */
#include "rows.h"

#define ALWAYS static inline __attribute__((always_inline))

/* recon.entropy.median.MEDIAN_COLUMNS: the columns that go through the network together. */
#define MEDIAN_COLUMNS 128

/* What every row of a call reads, and where it writes. */
struct median_args {
    const void *image;
    int64_t H, W;
    const int64_t *dy, *dx;
    int64_t n;
    const int64_t *pairs;
    int64_t n_pairs, rank;
    void *out;
};

/* The compare-exchange of rows a and b of m samples: the smaller of each pair at a, the larger at b. */
ALWAYS void exchange32(float *restrict a, float *restrict b, int64_t m) {
    for (int64_t x = 0; x < m; x++) {
        const float u = a[x];
        const float v = b[x];
        a[x] = u < v ? u : v;
        b[x] = u < v ? v : u;
    }
}

ALWAYS void exchange64(double *restrict a, double *restrict b, int64_t m) {
    for (int64_t x = 0; x < m; x++) {
        const double u = a[x];
        const double v = b[x];
        a[x] = u < v ? u : v;
        b[x] = u < v ? v : u;
    }
}

/* One row y of _median_kernel; samples of `size` bytes (4: float32, 8: float64). */
ALWAYS int median_row(const struct median_args *a, int wide, int64_t y) {
    const size_t size = wide ? 8 : 4;
    const int64_t H = a->H, W = a->W, n = a->n, block = MEDIAN_COLUMNS;
    char *buf = malloc((size_t)n * (size_t)block * size);
    if (!buf) return -1;
    for (int64_t x0 = 0; x0 < W; x0 += block) {
        const int64_t m = min64(block, W - x0);
        for (int64_t i = 0; i < n; i++) {
            const char *src = (const char *)a->image + min64(max64(y + a->dy[i], 0), H - 1) * W * (int64_t)size;
            char *row = buf + i * block * (int64_t)size;
            const int64_t d = a->dx[i];
            const int64_t lo = min64(max64(-d - x0, 0), m);  /* [lo, hi): x0 + x + d inside the image */
            const int64_t hi = min64(max64(W - d - x0, lo), m);
            for (int64_t x = 0; x < lo; x++) memcpy(row + x * (int64_t)size, src, size);
            if (hi > lo)
                memcpy(row + lo * (int64_t)size, src + (x0 + lo + d) * (int64_t)size, (size_t)(hi - lo) * size);
            for (int64_t x = hi; x < m; x++) memcpy(row + x * (int64_t)size, src + (W - 1) * (int64_t)size, size);
        }
        for (int64_t p = 0; p < a->n_pairs; p++) {
            char *ra = buf + a->pairs[2 * p] * block * (int64_t)size;
            char *rb = buf + a->pairs[2 * p + 1] * block * (int64_t)size;
            if (wide)
                exchange64((double *)ra, (double *)rb, m);
            else
                exchange32((float *)ra, (float *)rb, m);
        }
        memcpy((char *)a->out + (y * W + x0) * (int64_t)size, buf + a->rank * block * (int64_t)size, (size_t)m * size);
    }
    free(buf);
    return 0;
}

static int median_row32(void *ctx, int64_t y) { return median_row(ctx, 0, y); }

static int median_row64(void *ctx, int64_t y) { return median_row(ctx, 1, y); }

/* _median_kernel: out (H, W) the median of image (H, W) (float32, wide 0, or float64, wide 1, both
 * alike) over the n offsets (dy, dx) (n,) int64, by the selection network pairs (n_pairs, 2) int64 of
 * rank `rank` (its positions 0..n-1), rows dealt to `threads` threads. */
int lfrig_median(const void *image, int64_t wide, int64_t H, int64_t W, const int64_t *dy, const int64_t *dx,
                 int64_t n, const int64_t *pairs, int64_t n_pairs, int64_t rank, void *out, int64_t threads) {
    if (H <= 0 || W <= 0 || n <= 0) return 0;
    struct median_args a = {image, H, W, dy, dx, n, pairs, n_pairs, rank, out};
    return run_items(wide ? median_row64 : median_row32, &a, H, threads);
}
