/* The last steps of the matching-entropy estimator (recon/entropy/refine.py): the centroid correction
 * and the TV refinement of Eq. 13, compiled ahead of time so that they run without numba: each
 * function mirrors its numba twin operation for operation on the same types (no fused multiply-add,
 * no fast math), so it gives the same bits.
 *
 * - lfrig_centroid: _centroid_kernel;
 * - lfrig_tv_wavefront: _tv_wavefront, with _tv_row, _tv_dual_row, _tv_divergence_primal_row,
 *   _tv_dual and _tv_primal;
 * - lfrig_tv_blocks: _tv_blocks, with _copy_runs: the bands' threads are started once for the call,
 *   and each band's copy persists from round to round, taking the rows beyond its band from the
 *   other bands' copies between two barriers (numba's twin passes them through a second set of the
 *   maps: the same values).
 *
 * Arrays are C-contiguous; the comments of the numba twins say why each loop has its shape. numba's
 * max(a, b) is `b > a ? b : a` and min(a, b) `b < a ? b : a` (the first argument kept on a tie or a
 * NaN), so max(1.0, nan) is 1.0; x ** 2 is x * x. sqrt and division round correctly in both, packed
 * or not, so the loops the compiler vectorises give the scalar values. Where the CPU has AVX, the
 * dual step is written with its intrinsics, four columns at a time, so that it can leave out the
 * sqrt and the divisions where all four lie in the ball (tv_dual_run); elsewhere it is a plain loop.
 * Where two NaNs meet, which one's sign and payload the result carries is the machine's order of the
 * operands, which neither compiler keeps as written: NaNs are NaNs in both, not always the same bits.
 */
#include "rows.h"

#ifdef __AVX__
#include <immintrin.h>
#endif

/* refine.TV_WAVE_ITERATIONS: the iterations a band's sweep carries down its rows (no value depends on it). */
#define TV_WAVE_ITERATIONS 8

/* numba's max(a, b) and min(a, b) of floats. */
static inline double max_f64(double a, double b) { return b > a ? b : a; }
static inline double min_f64(double a, double b) { return b < a ? b : a; }

struct centroid_args {
    const double *d;
    const int64_t *rects;
    int64_t H, W;
    double max_residual, max_shift;
    double *out;
};

/* One row of _centroid_kernel. Each window holds its pixel (the caller checks: rects[.., 0] and
 * [.., 2] <= 0 <= rects[.., 1] and [.., 3]), so the clipped bounds are taken without overflow. */
static int centroid_row(void *ctx, int64_t y) {
    const struct centroid_args *a = ctx;
    const int64_t H = a->H, W = a->W;
    const double *restrict d = a->d;
    for (int64_t x = 0; x < W; x++) {
        const int64_t *r = a->rects + (y * W + x) * 4;
        const int64_t ya = r[0] < -y ? 0 : y + r[0];
        const int64_t yb = (r[1] > H - 1 - y ? H - 1 : y + r[1]) + 1;
        const int64_t xa = r[2] < -x ? 0 : x + r[2];
        const int64_t xb = (r[3] > W - 1 - x ? W - 1 : x + r[3]) + 1;
        if (ya + yb - 1 == 2 * y && xa + xb - 1 == 2 * x) { /* centred on the pixel: nothing to move */
            a->out[y * W + x] = d[y * W + x];
            continue;
        }
        double s1 = 0.0, sy = 0.0, sx = 0.0, s2 = 0.0;
        for (int64_t qy = ya; qy < yb; qy++) {
            const double *restrict row = d + qy * W;
            const double dy = (double)(qy - y);
            for (int64_t qx = xa; qx < xb; qx++) {
                const double v = row[qx];
                s1 += v;
                sy += v * dy;
                sx += v * (double)(qx - x);
                s2 += v * v;
            }
        }
        const int64_t ny = yb - ya, nx = xb - xa, n = ny * nx;
        const double cy = (double)(ya + yb - 1) / 2.0 - (double)y; /* centroid relative to the pixel */
        const double cx = (double)(xa + xb - 1) / 2.0 - (double)x;
        const double var_y = (double)(ny * ny - 1) / 12.0;
        const double var_x = (double)(nx * nx - 1) / 12.0;
        const double mean = s1 / (double)n;
        const double gy = var_y > 0 ? (sy / (double)n - cy * mean) / var_y : 0.0;
        const double gx = var_x > 0 ? (sx / (double)n - cx * mean) / var_x : 0.0;
        const double residual = s2 / (double)n - mean * mean - gy * gy * var_y - gx * gx * var_x;
        double value = d[y * W + x];
        if (residual <= a->max_residual * a->max_residual && (cy != 0.0 || cx != 0.0)) {
            const double shift = gy * cy + gx * cx;
            value -= min_f64(max_f64(shift, -a->max_shift), a->max_shift);
        }
        a->out[y * W + x] = value;
    }
    return 0;
}

/* _centroid_kernel: d (H, W) float64 corrected into out (H, W) float64 with each pixel's window
 * rects (H, W, 4) int64 (y0, y1, x0, x1, inclusive offsets); rows dealt to `threads` threads. */
int lfrig_centroid(const double *d, int64_t H, int64_t W, const int64_t *rects, double max_residual, double max_shift,
                   double *out, int64_t threads) {
    struct centroid_args a = {d, rects, H, W, max_residual, max_shift, out};
    return run_items(centroid_row, &a, H, threads);
}

/* The maps of one TV iteration over rows top .. top + n - 1 of an image of H rows, W columns (each
 * (n, W)), and the runs of the pixels it works on (tv_runs: per image row y, runs[y] .. runs[y + 1]
 * - 1 index x0, x1). */
struct tv_maps {
    const double *f;
    const uint8_t *mask;
    const double *weight;
    double *mu, *bar, *py, *px;
    int64_t n, W, top, H;
    const int64_t *runs;
    const uint64_t *x0, *x1;
};

/* _tv_dual: the dual step at one pixel from its forward differences gy, gx, in place on *py, *px. */
static inline void tv_dual(double *restrict py, double *restrict px, double gy, double gx, double sigma,
                           double gamma) {
    const double qy = *py + sigma * gy;
    const double qx = *px + sigma * gx;
    const double norm = max_f64(1.0, sqrt(qy * qy + qx * qx) / gamma);
    *py = qy / norm;
    *px = qx / norm;
}

/* mask ? a : b, chosen by the bits (a test of a byte that picks a double keeps GCC's loop scalar). */
static inline double pick(uint8_t mask, double a, double b) {
    const uint64_t m = (uint64_t)0 - (uint64_t)(mask != 0);
    uint64_t ia, ib;
    memcpy(&ia, &a, sizeof ia);
    memcpy(&ib, &b, sizeof ib);
    const uint64_t r = (ia & m) | (ib & ~m);
    double out;
    memcpy(&out, &r, sizeof out);
    return out;
}

/* _tv_primal: the primal step at one pixel from its divergence; the masked value is computed
 * everywhere and chosen. */
static inline double tv_primal(double f, uint8_t mask, double weight, double mu, double div, double tau) {
    const double v = mu + tau * div;
    const double w = 2.0 * tau * weight;
    return pick(mask, (v + w * f) / (1.0 + w), f);
}

/* The largest s (or one a little less) whose sqrt rounds to at most gamma: where the squared norm
 * of the new dual values is at most this, their norm over gamma rounds to at most 1, numba's max
 * makes it 1 and the divisions by it leave them as they are. -1 (no s) where gamma is not > 0 and
 * finite. */
static double ball_bound(double gamma) {
    if (!(gamma > 0.0) || gamma == INFINITY) return -1.0;
    double s = gamma * gamma;
    while (s > 0.0 && sqrt(s) > gamma) { /* the next double towards 0 */
        uint64_t bits;
        memcpy(&bits, &s, sizeof bits);
        bits--;
        memcpy(&s, &bits, sizeof s);
    }
    return s;
}

/* tv_dual over columns x0 .. end - 1 of a row (the forward difference in x inside the row). Where
 * the CPU has AVX, four columns at a time, whose sqrt and divisions (the step's cost: sqrt and
 * division take one unit, which the other operations wait for) are left out where all four new
 * values lie in the ball (ball_bound: the divisions by a norm of 1 would leave them as they are),
 * as they do for about half the columns over the refinement's iterations; the same values. */
static inline void tv_dual_run(double *restrict qy, double *restrict qx, const double *restrict b0,
                               const double *restrict b1, int below, double sigma, double gamma, double bound,
                               uint64_t x0, uint64_t end) {
    uint64_t x = x0;
#ifdef __AVX__
    const __m256d vs = _mm256_set1_pd(sigma), vg = _mm256_set1_pd(gamma), vb = _mm256_set1_pd(bound);
    const __m256d one = _mm256_set1_pd(1.0);
    for (; x + 4 <= end; x += 4) {
        const __m256d c = _mm256_loadu_pd(b0 + x);
        const __m256d gy = below ? _mm256_sub_pd(_mm256_loadu_pd(b1 + x), c) : _mm256_setzero_pd();
        const __m256d gx = _mm256_sub_pd(_mm256_loadu_pd(b0 + x + 1), c);
        __m256d ty = _mm256_add_pd(_mm256_loadu_pd(qy + x), _mm256_mul_pd(vs, gy));
        __m256d tx = _mm256_add_pd(_mm256_loadu_pd(qx + x), _mm256_mul_pd(vs, gx));
        const __m256d s = _mm256_add_pd(_mm256_mul_pd(ty, ty), _mm256_mul_pd(tx, tx));
        if (_mm256_movemask_pd(_mm256_cmp_pd(s, vb, _CMP_LE_OQ)) != 0xf) {
            const __m256d norm = _mm256_max_pd(_mm256_div_pd(_mm256_sqrt_pd(s), vg), one); /* max(1.0, t) */
            ty = _mm256_div_pd(ty, norm);
            tx = _mm256_div_pd(tx, norm);
        }
        _mm256_storeu_pd(qy + x, ty);
        _mm256_storeu_pd(qx + x, tx);
    }
#else
    (void)bound;
#endif
    if (below) {
        for (; x < end; x++) tv_dual(qy + x, qx + x, b1[x] - b0[x], b0[x + 1] - b0[x], sigma, gamma);
    } else {
        for (; x < end; x++) tv_dual(qy + x, qx + x, 0.0, b0[x + 1] - b0[x], sigma, gamma);
    }
}

/* _tv_dual_row: the dual step along the runs r0 .. r1 - 1 of a row, in place on its dual values qy,
 * qx, from its primal values b0 and, if `below`, the next row's b1 (else the y difference is 0). */
static void tv_dual_row(double *restrict qy, double *restrict qx, const double *restrict b0,
                        const double *restrict b1, int below, double sigma, double gamma, double bound, uint64_t W,
                        const uint64_t *run_x0, const uint64_t *run_x1, int64_t r0, int64_t r1) {
    const uint64_t m = W - 1;
    for (int64_t r = r0; r < r1; r++) {
        const uint64_t x0 = run_x0[r], x1 = run_x1[r];
        tv_dual_run(qy, qx, b0, b1, below, sigma, gamma, bound, x0, x1 < m ? x1 : m);
        if (x1 > m) tv_dual(qy + m, qx + m, below ? b1[m] - b0[m] : 0.0, 0.0, sigma, gamma);
    }
}

/* _tv_divergence_primal_row: along the runs r0 .. r1 - 1 of a row, the divergence into div from its
 * dual values qy, qx and the row above's y part `above` (edge 0 on the first row, no row above; 1
 * inside; 2 on the last row), then the primal step, in place on its mu and bar. */
static void tv_divergence_primal_row(const double *restrict f, const uint8_t *restrict mask,
                                     const double *restrict weight, double *restrict mu, double *restrict bar,
                                     double *restrict div, const double *restrict qy, const double *restrict qx,
                                     const double *restrict above, int edge, double tau, uint64_t W,
                                     const uint64_t *run_x0, const uint64_t *run_x1, int64_t r0, int64_t r1) {
    const uint64_t m = W - 1;
    for (int64_t r = r0; r < r1; r++) {
        const uint64_t x0 = run_x0[r], x1 = run_x1[r];
        if (edge == 0) {
            for (uint64_t x = x0; x < x1; x++) div[x] = qy[x];
        } else if (edge == 1) {
            for (uint64_t x = x0; x < x1; x++) div[x] = qy[x] - above[x];
        } else {
            for (uint64_t x = x0; x < x1; x++) div[x] = -above[x];
        }
        if (x0 == 0) div[0] += qx[0];
        const uint64_t start = x0 > 1 ? x0 : 1, end = x1 < m ? x1 : m;
        for (uint64_t x = start; x < end; x++) div[x] += qx[x] - qx[x - 1];
        if (x1 > m) div[m] += -qx[m - 1];
        for (uint64_t x = x0; x < x1; x++) {
            const double new = tv_primal(f[x], mask[x], weight[x], mu[x], div[x], tau);
            bar[x] = 2.0 * new - mu[x];
            mu[x] = new;
        }
    }
}

/* _tv_row: one iteration at row i of the maps over its runs (image row top + i): the dual step
 * (reads bar's rows i and i + 1), then the primal step (reads py's rows i - 1 and i, writes bar's
 * and mu's row i). div: (W,) scratch. */
static void tv_row(const struct tv_maps *s, int64_t i, double gamma, double bound, double tau, double sigma,
                   double *restrict div) {
    const int64_t n = s->n, W = s->W, H = s->H, y = s->top + i;
    const int64_t r0 = s->runs[y], r1 = s->runs[y + 1];
    if (r0 == r1) return;
    const int below = y < H - 1 && i < n - 1;
    double *py = s->py + i * W, *px = s->px + i * W, *bar = s->bar + i * W;
    tv_dual_row(py, px, bar, below ? bar + W : bar, below, sigma, gamma, bound, (uint64_t)W, s->x0, s->x1, r0, r1);
    const int edge = y == 0 || i == 0 ? 0 : y < H - 1 ? 1 : 2;
    tv_divergence_primal_row(s->f + i * W, s->mask + i * W, s->weight + i * W, s->mu + i * W, bar, div, py, px,
                             i > 0 ? py - W : py, edge, tau, (uint64_t)W, s->x0, s->x1, r0, r1);
}

/* _tv_wavefront: `iterations` iterations of the maps, `depth` at a time in one sweep down the rows,
 * iteration t + 1 one row behind iteration t. div: (W,) scratch. */
static void tv_wavefront(const struct tv_maps *s, double gamma, int64_t iterations, int64_t depth, double *div) {
    const double tau = 1.0 / sqrt(8.0);
    const double sigma = tau;
    const double bound = ball_bound(gamma);
    const int64_t n = s->n;
    if (depth < 1) depth = 1; /* (no value depends on it) */
    for (int64_t done = 0; done < iterations;) {
        const int64_t k = min64(depth, iterations - done);
        for (int64_t front = 0; front < n + k - 1; front++) {
            for (int64_t j = 0; j < k; j++) {
                const int64_t i = front - j;
                if (0 <= i && i < n) tv_row(s, i, gamma, bound, tau, sigma, div);
            }
        }
        done += k;
    }
}

/* _tv_wavefront: f, weight (n, W) float64, mask (n, W) uint8 (numpy bool) and the state mu, bar, py,
 * px (n, W) float64, iterated in place: the rows top .. top + n - 1 of an image of H rows; runs (H +
 * 1,) int64, run_x0, run_x1 uint64 (tv_runs). On this thread. */
int lfrig_tv_wavefront(const double *f, const uint8_t *mask, const double *weight, int64_t n, int64_t W, double gamma,
                       int64_t iterations, double *mu, double *bar, double *py, double *px, int64_t top, int64_t H,
                       int64_t depth, const int64_t *runs, const uint64_t *run_x0, const uint64_t *run_x1) {
    if (n <= 0 || W <= 0 || iterations <= 0) return 0;
    double *div = malloc(sizeof(double) * (size_t)W);
    if (!div) return -1;
    const struct tv_maps s = {f, mask, weight, mu, bar, py, px, n, W, top, H, runs, run_x0, run_x1};
    tv_wavefront(&s, gamma, iterations, depth, div);
    free(div);
    return 0;
}

/* _copy_runs: the values of the runs of image rows [y0, y1) from the four maps of `source` (rows
 * from source_top) into those of `target` (rows from target_top). */
static void copy_runs(double *const *source, double *const *target, int64_t source_top, int64_t target_top, int64_t y0,
                      int64_t y1, int64_t W, const int64_t *runs, const uint64_t *run_x0, const uint64_t *run_x1) {
    for (int64_t y = y0; y < y1; y++) {
        for (int64_t r = runs[y]; r < runs[y + 1]; r++) {
            const uint64_t a = run_x0[r], b = run_x1[r];
            for (int j = 0; j < 4; j++)
                memcpy(target[j] + (y - target_top) * W + a, source[j] + (y - source_top) * W + a,
                       sizeof(double) * (b - a));
        }
    }
}

/* What the bands of a lfrig_tv_blocks call read and write: the image's f, mask and weight, the four
 * maps (mu, bar, py, px) they start from and end in, and each band's copy (depth rows of the four
 * maps, from the band's first row less halo) and scratch row. */
struct blocks_args {
    const double *f;
    const uint8_t *mask;
    const double *weight;
    int64_t H, W;
    double gamma;
    int64_t iterations;
    double *maps[4];
    const int64_t *edges;
    int64_t n_blocks, halo, depth;
    const int64_t *runs;
    const uint64_t *x0, *x1;
    double *copies, *div;
};

/* Band b's copy's first image row, and its four maps. */
static int64_t copy_top(const struct blocks_args *a, int64_t b) { return max64(a->edges[b] - a->halo, 0); }

static void copy_maps(const struct blocks_args *a, int64_t b, double **maps) {
    for (int j = 0; j < 4; j++) maps[j] = a->copies + ((b * 4 + j) * a->depth) * a->W;
}

/* The runs of image rows [y0, y1) into band b's copy from the copies of the bands they are in. */
static void take_rows(const struct blocks_args *a, int64_t b, int64_t y0, int64_t y1) {
    double *own[4], *other[4];
    copy_maps(a, b, own);
    for (int64_t o = 0; o < a->n_blocks; o++) {
        const int64_t u0 = max64(y0, a->edges[o]), u1 = min64(y1, a->edges[o + 1]);
        if (o == b || u0 >= u1) continue;
        copy_maps(a, o, other);
        copy_runs(other, own, copy_top(a, o), copy_top(a, b), u0, u1, a->W, a->runs, a->x0, a->x1);
    }
}

/* Thread t of T's share of _tv_blocks: bands t, t + T, ... Each band's copy takes its rows from the
 * maps, then, round after round, is iterated `halo` iterations (the last round fewer) and takes the
 * rows beyond its band from the bands they are in (the values numba's twin exchanges through a
 * second set of maps: the same values, with two barriers a round instead of one, and each band's
 * rows copied out once, not once a round); at the end each band's rows go into the maps. */
static void blocks_share(const struct blocks_args *a, struct crew *c, int64_t t) {
    const int64_t H = a->H, W = a->W, halo = a->halo, T = c->count;
    for (int64_t b = t; b < a->n_blocks; b += T) {
        const int64_t top = copy_top(a, b), z = min64(a->edges[b + 1] + halo, H);
        double *own[4];
        copy_maps(a, b, own);
        for (int j = 0; j < 4; j++) memcpy(own[j], a->maps[j] + top * W, sizeof(double) * (size_t)((z - top) * W));
    }
    for (int64_t done = 0; done < a->iterations;) {
        const int64_t k = min64(halo, a->iterations - done);
        if (done > 0) {
            crew_barrier(c); /* every band's rows are those of `done` iterations */
            for (int64_t b = t; b < a->n_blocks; b += T) {
                take_rows(a, b, copy_top(a, b), a->edges[b]);
                take_rows(a, b, a->edges[b + 1], min64(a->edges[b + 1] + halo, H));
            }
        }
        crew_barrier(c); /* every copy has its rows: the bands may change theirs */
        for (int64_t b = t; b < a->n_blocks; b += T) {
            const int64_t top = copy_top(a, b), z = min64(a->edges[b + 1] + halo, H);
            double *own[4];
            copy_maps(a, b, own);
            const struct tv_maps s = {a->f + top * W, a->mask + top * W, a->weight + top * W, own[0], own[1], own[2],
                                      own[3], z - top, W, top, H, a->runs, a->x0, a->x1};
            tv_wavefront(&s, a->gamma, k, TV_WAVE_ITERATIONS, a->div + b * W);
        }
        done += k;
    }
    for (int64_t b = t; b < a->n_blocks; b += T) {
        double *own[4];
        copy_maps(a, b, own);
        copy_runs(own, a->maps, copy_top(a, b), 0, a->edges[b], a->edges[b + 1], W, a->runs, a->x0, a->x1);
    }
}

/* blocks_share as run_crew calls it. */
static void blocks_crew(const void *a, struct crew *c, int64_t t) { blocks_share(a, c, t); }

/* _tv_blocks: the image (H, W) in n_blocks bands of rows [edges[b], edges[b + 1]) (edges (n_blocks
 * + 1,) int64, ascending from 0 to H), each iterated on a copy of its own with `halo` rows around it,
 * `halo` iterations at a time, on `threads` threads (at most n_blocks) started once for the call.
 * The arguments as lfrig_tv_wavefront's; the state mu, bar, py, px ends in place, as one sweep over
 * the whole image leaves it (numba's twin returns its mu). */
int lfrig_tv_blocks(const double *f, const uint8_t *mask, const double *weight, int64_t H, int64_t W, double gamma,
                    int64_t iterations, double *mu, double *bar, double *py, double *px, const int64_t *edges,
                    int64_t n_blocks, int64_t halo, const int64_t *runs, const uint64_t *run_x0,
                    const uint64_t *run_x1, int64_t threads) {
    if (H <= 0 || W <= 0 || n_blocks <= 0 || iterations <= 0) return 0;
    if (halo < 1) halo = 1; /* the rows a copy reaches beyond its band: none would be no band's */
    int64_t depth = 0;
    for (int64_t b = 0; b < n_blocks; b++)
        depth = max64(depth, min64(edges[b + 1] + halo, H) - max64(edges[b] - halo, 0));
    const int64_t T = max64(min64(threads, n_blocks), 1);
    struct blocks_args a = {f, mask, weight, H, W, gamma, iterations, {mu, bar, py, px}, edges, n_blocks, halo,
                            depth, runs, run_x0, run_x1, NULL, NULL};
    a.copies = malloc(sizeof(double) * (size_t)(n_blocks * 4 * depth * W));
    a.div = malloc(sizeof(double) * (size_t)(n_blocks * W));
    int status = 0;
    if (!a.copies || !a.div) {
        status = -1;
        goto done;
    }
    status = run_crew(blocks_crew, &a, T);
done:
    free(a.copies);
    free(a.div);
    return status;
}
