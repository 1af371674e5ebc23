/* The distance to the nearest disparity jump of the confidence model (recon/entropy/calibration.py,
 * jump_distance), compiled ahead of time: scipy's exact Euclidean distance transform of the pixels
 * beside a jump, capped, with the same bits.
 *
 * - lfrig_jump_distance: rows [r0, r1) of min(sqrt(d2), reach), d2 the squared distance (pixels) from
 *   a pixel to the nearest pixel on either side of a step |d[q] - d[p]| > jump between 4-neighbours
 *   p, q of the (H, W) float64 map d (the test as numpy takes it: the difference, its magnitude, the
 *   comparison; a NaN step is none).
 *
 * In integers, one axis after the other: down each column the rows to the nearest marked pixel
 * (capped at reach + 1: farther counts as none), then along each row the least dx^2 + g^2 over the
 * columns |dx| <= reach. A pixel within reach of a marked one has that one within reach along both
 * axes, so its d2 is exact; a farther one gets at least (reach + 1)^2, and so the cap. The square root
 * of the integer d2 (capped at reach^2) is correctly rounded, as numpy's of scipy's float64
 * dy^2 + dx^2 of the nearest marked pixel; sqrt(reach^2) is reach. Integer sums: any order.
 * Arrays are C-contiguous; one thread (the confidence step runs bands in threads of its own).
 */
#ifdef __AVX__
#include <immintrin.h>
#endif
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

static inline int32_t least(int32_t a, int32_t b) { return a < b ? a : b; }

int lfrig_jump_distance(const double *d, int64_t H, int64_t W, double jump, int64_t reach, int64_t r0,
                        int64_t r1, double *out) {
    if (r1 <= r0 || W <= 0) return 0;
    const int64_t n = r1 - r0;
    uint8_t *mark = calloc((size_t)(H * W), 1);
    int32_t *g = malloc(sizeof(int32_t) * (size_t)(n * W));     /* rows [r0, r1): the column distance */
    int32_t *run = malloc(sizeof(int32_t) * (size_t)W);         /* the scan's distance in each column */
    int32_t *best = malloc(sizeof(int32_t) * (size_t)W);
    if (!mark || !g || !run || !best) {
        free(mark);
        free(g);
        free(run);
        free(best);
        return -1;
    }
    /* the pixels on either side of a step: down the columns (np.diff along axis 0), along the rows */
    for (int64_t y = 0; y < H; y++) {
        const double *row = d + y * W;
        uint8_t *m = mark + y * W;
        if (y + 1 < H) {
            const double *below = row + W;
            uint8_t *mb = m + W;
            for (int64_t x = 0; x < W; x++) {
                const uint8_t step = fabs(below[x] - row[x]) > jump;
                m[x] |= step;
                mb[x] |= step;
            }
        }
        for (int64_t x = 0; x + 1 < W; x++) {
            const uint8_t step = fabs(row[x + 1] - row[x]) > jump;
            m[x] |= step;
            m[x + 1] |= step;
        }
    }
    /* down the columns: rows to the nearest marked pixel above (first scan) and below (second) */
    const int32_t far = (int32_t)(reach + 1);
    for (int64_t x = 0; x < W; x++) run[x] = far;
    for (int64_t y = 0; y < r1; y++) {
        const uint8_t *m = mark + y * W;
        for (int64_t x = 0; x < W; x++) run[x] = m[x] ? 0 : least(run[x] + 1, far);
        if (y >= r0) {
            int32_t *gy = g + (y - r0) * W;
            for (int64_t x = 0; x < W; x++) gy[x] = run[x];
        }
    }
    for (int64_t x = 0; x < W; x++) run[x] = far;
    for (int64_t y = H - 1; y >= r0; y--) {
        const uint8_t *m = mark + y * W;
        for (int64_t x = 0; x < W; x++) run[x] = m[x] ? 0 : least(run[x] + 1, far);
        if (y < r1) {
            int32_t *gy = g + (y - r0) * W;
            for (int64_t x = 0; x < W; x++) gy[x] = least(gy[x], run[x]);
        }
    }
    /* along the rows: the least dx^2 + g^2 within reach, capped at reach^2, and its square root */
    const int32_t cap = (int32_t)(reach * reach);
    for (int64_t i = 0; i < n; i++) {
        int32_t *gy = g + i * W;
        for (int64_t x = 0; x < W; x++) {
            gy[x] = gy[x] * gy[x];
            best[x] = cap;
        }
        for (int64_t dx = -reach; dx <= reach; dx++) {
            const int32_t dd = (int32_t)(dx * dx);
            const int64_t x0 = dx < 0 ? -dx : 0, x1 = dx > 0 ? W - dx : W;
            for (int64_t x = x0; x < x1; x++) best[x] = least(best[x], dd + gy[x + dx]);
        }
        double *o = out + i * W;
        for (int64_t x = 0; x < W; x++) o[x] = sqrt((double)best[x]);
    }
    free(mark);
    free(g);
    free(run);
    free(best);
    return 0;
}

/* - lfrig_neighbours: rows [r0, r1) of the (H, W) float64 map d (finite: the caller checks) as
 *   recon.entropy.calibration's Band takes them from numpy: `nearest`, the least |d - d_n| over the 8
 *   neighbours (np.minimum from +inf, in the order of neighbour_agreement's loops; the border
 *   continued by the nearest pixel), `agreeing`, how many of them have |d - d_n| <= tolerance, and
 *   `slope`, np.hypot of np.gradient's two derivatives (central differences halved inside, one-sided
 *   at the map's first and last row or column, 0 along an axis of one pixel). hypot is the C
 *   library's, which numpy's np.hypot calls too. With `nearest` NULL only the slope (`agreeing` unused). */
static inline double at(const double *d, int64_t H, int64_t W, int64_t y, int64_t x) {
    y = y < 0 ? 0 : (y >= H ? H - 1 : y);
    x = x < 0 ? 0 : (x >= W ? W - 1 : x);
    return d[y * W + x];
}

static inline double derivative(const double *d, int64_t n, int64_t i, int64_t stride) {
    if (n < 2) return 0.0;
    if (i == 0) return (d[stride] - d[0]) / 1.0;
    if (i == n - 1) return (d[i * stride] - d[(i - 1) * stride]) / 1.0;
    return (d[(i + 1) * stride] - d[(i - 1) * stride]) / 2.0;
}

/* The 8 neighbours of columns [x0, x1) of a row (its rows above and below clamped by the caller;
 * x0 >= 1 and x1 <= W - 1 there, so that no column is clamped): np.minimum from +inf and the
 * count, in neighbour_agreement's order (the row above left to right, the row's left and right, the
 * row below). `least < diff ? least : diff` is np.minimum of numbers, and vectorises. */
static void neighbours_run(const double *up, const double *mid, const double *down, int64_t x0, int64_t x1,
                           double tolerance, double *nearest, int64_t *agreeing) {
    for (int64_t x = x0; x < x1; x++) {
        const double v = mid[x];
        const double n[8] = {up[x - 1], up[x], up[x + 1], mid[x - 1], mid[x + 1], down[x - 1], down[x], down[x + 1]};
        double least = INFINITY;
        int64_t count = 0;
        for (int k = 0; k < 8; k++) {
            const double diff = fabs(v - n[k]);
            least = least < diff ? least : diff;
            count += diff <= tolerance;
        }
        nearest[x] = least;
        agreeing[x] = count;
    }
}

/* The same at a column that may be clamped (the first and the last). */
static void neighbours_at(const double *d, int64_t H, int64_t W, int64_t y, int64_t x, double tolerance,
                          double *nearest, int64_t *agreeing) {
    const double v = d[y * W + x];
    double least = INFINITY;
    int64_t count = 0;
    for (int64_t dy = -1; dy <= 1; dy++) {
        for (int64_t dx = -1; dx <= 1; dx++) {
            if (dy == 0 && dx == 0) continue;
            const double diff = fabs(v - at(d, H, W, y + dy, x + dx));
            least = least < diff ? least : diff;  /* np.minimum(least, diff) of numbers */
            count += diff <= tolerance;
        }
    }
    nearest[x] = least;
    agreeing[x] = count;
}

int lfrig_neighbours(const double *d, int64_t H, int64_t W, int64_t r0, int64_t r1, double tolerance,
                     double *nearest, int64_t *agreeing, double *slope) {
    double *gy = malloc(sizeof(double) * (size_t)(2 * W)), *gx = gy + W;
    if (!gy) return -1;
    for (int64_t y = r0; y < r1; y++) {
        const int64_t i = (y - r0) * W;
        if (nearest) {
            const double *mid = d + y * W;
            const double *up = d + (y > 0 ? y - 1 : 0) * W, *down = d + (y + 1 < H ? y + 1 : H - 1) * W;
            neighbours_at(d, H, W, y, 0, tolerance, nearest + i, agreeing + i);
            if (W > 2) neighbours_run(up, mid, down, 1, W - 1, tolerance, nearest + i, agreeing + i);
            if (W > 1) neighbours_at(d, H, W, y, W - 1, tolerance, nearest + i, agreeing + i);
        }
        for (int64_t x = 0; x < W; x++) {
            gy[x] = derivative(d + x, H, y, W);
            gx[x] = derivative(d + y * W, W, x, 1);
        }
#ifdef __AVX__
        /* the loops above may leave the vector registers' upper halves in use, and the C library's
         * hypot (SSE code) then runs several times slower on some CPUs */
        _mm256_zeroupper();
#endif
        for (int64_t x = 0; x < W; x++) slope[i + x] = hypot(gy[x], gx[x]);
    }
    free(gy);
    return 0;
}
