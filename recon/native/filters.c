/* scipy.ndimage's uniform filter along one axis of an image (recon/entropy/filters.py), so that an
 * estimate needs no scipy.ndimage (its import takes ~0.1 s of Python): the same arithmetic in the same
 * order as scipy's NI_UniformFilter1D, so it gives the same bits.
 *
 * - lfrig_uniform: scipy.ndimage.uniform_filter1d(image, size, axis, mode=...) of an (H, W) float32
 *   (wide 0) or float64 (wide 1) image into an image of the same type, for modes "nearest" (0: the
 *   edge value repeated) and "reflect" (1: d c b a | a b c d, repeated for lines shorter than the
 *   window).
 *
 * scipy copies each line into a float64 buffer extended by size / 2 samples before it and
 * size - size / 2 - 1 after it, sums the first `size` samples in order, and then moves the window one
 * sample at a time: the running sum gains the sample that enters and loses the one that leaves
 * (sum += entering - leaving, in float64), and each output is sum / size rounded to the output's
 * type. Along rows (axis 1) a row is copied into such a buffer, so the output may be the input. Along
 * columns (axis 0) every column of a row moves at once, each with its own running sum: the same
 * operations for each column in the same order, so the same bits; the output must not be the input.
 */
#include <stdint.h>
#include <stdlib.h>

/* The index of the sample at i (which may lie outside [0, n)) after the line's extension by `mode`. */
static int64_t extended(int64_t i, int64_t n, int64_t mode) {
    if (i >= 0 && i < n) return i;
    if (mode == 0) return i < 0 ? 0 : n - 1;
    const int64_t period = 2 * n;
    int64_t j = i % period;
    if (j < 0) j += period;
    return j < n ? j : period - 1 - j;
}

static double sample(const void *image, int wide, int64_t at) {
    return wide ? ((const double *)image)[at] : (double)((const float *)image)[at];
}

static void put(void *image, int wide, int64_t at, double value) {
    if (wide)
        ((double *)image)[at] = value;
    else
        ((float *)image)[at] = (float)value;
}

/* Along each row: the row copied into the extended float64 buffer `line` (W + size - 1 samples). */
static void along_rows(const void *in, void *out, int wide, int64_t H, int64_t W, int64_t size, int64_t mode,
                       double *line) {
    const int64_t before = size / 2;
    for (int64_t y = 0; y < H; y++) {
        for (int64_t i = 0; i < W + size - 1; i++) line[i] = sample(in, wide, y * W + extended(i - before, W, mode));
        double sum = 0.0;
        for (int64_t i = 0; i < size; i++) sum += line[i];
        put(out, wide, y * W, sum / (double)size);
        for (int64_t x = 1; x < W; x++) {
            sum += line[x + size - 1] - line[x - 1];
            put(out, wide, y * W + x, sum / (double)size);
        }
    }
}

/* Along each column, a row of columns at a time: `sums` holds the W running sums. */
static void along_columns(const void *in, void *out, int wide, int64_t H, int64_t W, int64_t size, int64_t mode,
                          double *sums) {
    const int64_t before = size / 2;
    for (int64_t x = 0; x < W; x++) sums[x] = 0.0;
    for (int64_t i = 0; i < size; i++) {
        const int64_t row = extended(i - before, H, mode) * W;
        for (int64_t x = 0; x < W; x++) sums[x] += sample(in, wide, row + x);
    }
    for (int64_t x = 0; x < W; x++) put(out, wide, x, sums[x] / (double)size);
    for (int64_t y = 1; y < H; y++) {
        const int64_t entering = extended(y + size - 1 - before, H, mode) * W;
        const int64_t leaving = extended(y - 1 - before, H, mode) * W;
        for (int64_t x = 0; x < W; x++) {
            sums[x] += sample(in, wide, entering + x) - sample(in, wide, leaving + x);
            put(out, wide, y * W + x, sums[x] / (double)size);
        }
    }
}

/* scipy.ndimage.uniform_filter1d of the (H, W) image `in` along `axis` (0 or 1) into `out` (the same
 * type: float32 for wide 0, float64 for wide 1; along rows it may be `in` itself). size >= 1,
 * mode 0 nearest or 1 reflect. Returns 0, -1 out of memory, -3 bad arguments. */
int lfrig_uniform(const void *in, void *out, int64_t wide, int64_t H, int64_t W, int64_t size, int64_t axis,
                  int64_t mode) {
    if (H < 1 || W < 1 || size < 1 || (axis != 0 && axis != 1) || (mode != 0 && mode != 1) || (axis == 0 && in == out))
        return -3;
    double *scratch = malloc((size_t)(axis == 1 ? W + size - 1 : W) * sizeof(double));
    if (!scratch) return -1;
    if (axis == 1)
        wide ? along_rows(in, out, 1, H, W, size, mode, scratch) : along_rows(in, out, 0, H, W, size, mode, scratch);
    else
        wide ? along_columns(in, out, 1, H, W, size, mode, scratch)
             : along_columns(in, out, 0, H, W, size, mode, scratch);
    free(scratch);
    return 0;
}
