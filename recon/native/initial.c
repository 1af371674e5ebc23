/* The kernels of the matching-entropy estimator's first phase (the nine-view search of
 * recon/entropy/initial.py), compiled ahead of time so that the phase runs before numba has
 * started: each mirrors its numba twin operation for operation on the same types (no fused
 * multiply-add, no fast math), so it gives the same bits.
 *
 * - lfrig_min_window_costs: recon/entropy/cost.py, _min_window_costs_kernel (with _block_rows,
 *   _block_view_rows, _view_row and _set_sum, whose mirrors tables.h holds);
 * - lfrig_subpixel_argmin: recon/entropy/matching.py, _subpixel_argmin_kernel;
 * - lfrig_cost_ambiguity: recon/entropy/cost.py, _cost_ambiguity_kernel;
 * - lfrig_downsample: recon/entropy/initial.py, _downsample_kernel.
 *
 * Arrays are C-contiguous; the comments of the numba twins say why each loop has its shape.
 *
 * Built for a CPU with AVX-512, the loops vectorise over 512-bit registers (GCC's -march=native
 * takes 256 for some of them, Intel's among them): the same operations lane by lane, no sum
 * reordered, so the same bits; on backgammon the nine-view search's window costs took 0.37 -> 0.30 s
 * on one thread.
 */
#if defined(__AVX512F__) && defined(__GNUC__) && !defined(__clang__)
#pragma GCC target("prefer-vector-width=512")
#endif
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wunused-function" /* set_sum: here fixed_set_rows makes the sets' rows */
#include "tables.h"
#pragma GCC diagnostic pop

struct mwc_args {
    struct views v;
    const float *disparities;
    int64_t G;
    const int64_t *set_blocks, *set_from, *set_order;
    int64_t S;
    const int64_t *window_set, *rects;
    int64_t K;
    const double *counts;
    const uint8_t *allowed;
    int64_t aH, aW;
    int64_t n_chunks;
    float *out;
};

/* Pixels a pass of fixed_set_rows takes at once: a set's sum over them stays in registers. */
#define SET_TILE 64

/* _set_sum for every set (in set_order) and each value rounded to a multiple of 1 / FIXED_POINT into
 * slot (S, W), TILE pixels at a time: a set's blocks added in registers (each pixel's float64 sum the
 * same additions in the same order as set_sum's passes), the tile's sums kept in sums (S, SET_TILE)
 * for the sets that continue them. first, from, count: per set, its first block's row that it adds
 * (after set_from's sum, or as its start), the set it continues (-1: none) and how many rows it adds;
 * rows_of[s * N_BLOCKS + j] its j-th block row. */
static void fixed_set_rows(const float *const *rows_of, const int64_t *from, const int64_t *count,
                           const int64_t *order, int64_t S, int64_t W, double *tile, double *slot) {
    for (int64_t x0 = 0; x0 < W; x0 += SET_TILE) {
        const int64_t n = min64(SET_TILE, W - x0);
        for (int64_t i = 0; i < S; i++) {
            const int64_t s = order[i];
            const float *const *r = rows_of + s * N_BLOCKS;
            double *restrict v = tile + s * SET_TILE;
            double *restrict fixed = slot + s * W + x0;
            if (n == SET_TILE) {
                double t[SET_TILE];
                if (from[s] >= 0) {
                    const double *restrict before = tile + from[s] * SET_TILE;
                    for (int64_t x = 0; x < SET_TILE; x++) t[x] = before[x] + (double)r[0][x0 + x];
                } else {
                    for (int64_t x = 0; x < SET_TILE; x++) t[x] = (double)r[0][x0 + x];
                }
                for (int64_t j = 1; j < count[s]; j++)
                    for (int64_t x = 0; x < SET_TILE; x++) t[x] += (double)r[j][x0 + x];
                for (int64_t x = 0; x < SET_TILE; x++) {
                    v[x] = t[x];
                    fixed[x] = floor(t[x] * FIXED_POINT + 0.5);
                }
            } else {
                if (from[s] >= 0) {
                    const double *restrict before = tile + from[s] * SET_TILE;
                    for (int64_t x = 0; x < n; x++) v[x] = before[x] + (double)r[0][x0 + x];
                } else {
                    for (int64_t x = 0; x < n; x++) v[x] = (double)r[0][x0 + x];
                }
                for (int64_t j = 1; j < count[s]; j++)
                    for (int64_t x = 0; x < n; x++) v[x] += (double)r[j][x0 + x];
                for (int64_t x = 0; x < n; x++) fixed[x] = floor(v[x] * FIXED_POINT + 0.5);
            }
        }
    }
}

/* A window of a row for the pixels its window covers whole in x: its column sums, gate row (NULL:
 * every pixel), first column offset, width, pixels [lo, hi) and denominator. */
struct inner {
    const double *col;
    const uint8_t *al;
    int64_t ra, width, lo, hi;
    double denom;
    int done;
};

/* Whether two doubles have the same bits. */
static inline int same_bits(double a, double b) {
    uint64_t p, q;
    memcpy(&p, &a, sizeof p);
    memcpy(&q, &b, sizeof q);
    return p == q;
}

/* The window's sum at pixels [xa, xb) from its column sums s0 = col + xa + ra (_min_window_costs_kernel's
 * additions, by width), as v(i, t) takes it. */
#define WINDOW_SUMS(w, xa, xb, body)                                                                              \
    do {                                                                                                          \
        const int64_t n_ = (xb) - (xa);                                                                           \
        const double *restrict s0 = (w)->col + (xa) + (w)->ra;                                                    \
        const double *restrict s1 = s0 + 1;                                                                       \
        const double *restrict s2 = s0 + 2;                                                                       \
        if ((w)->width == 5) {                                                                                    \
            const double *restrict s3 = s0 + 3;                                                                   \
            const double *restrict s4 = s0 + 4;                                                                   \
            for (int64_t i = 0; i < n_; i++) {                                                                    \
                const double t = ((s0[i] + s1[i]) + (s2[i] + s3[i])) + s4[i];                                     \
                body;                                                                                             \
            }                                                                                                     \
        } else if ((w)->width == 3) {                                                                             \
            for (int64_t i = 0; i < n_; i++) {                                                                    \
                const double t = (s0[i] + s1[i]) + s2[i];                                                         \
                body;                                                                                             \
            }                                                                                                     \
        } else {                                                                                                  \
            for (int64_t i = 0; i < n_; i++) {                                                                    \
                double t = s0[i];                                                                                 \
                for (int64_t q = 1; q < (w)->width; q++) t += s0[i + q];                                          \
                body;                                                                                             \
            }                                                                                                     \
        }                                                                                                         \
    } while (0)

/* The window's costs at pixels [xa, xb) into best (the least), a division each. */
static void window_costs(double *restrict best, const struct inner *w, int64_t xa, int64_t xb) {
    if (xb <= xa) return;
    double *restrict bs = best + xa;
    const uint8_t *restrict al = w->al ? w->al + xa : NULL;
    const double denom = w->denom;
    WINDOW_SUMS(w, xa, xb, {
        double c = t * FIXED_INV / denom;
        c = (!al || al[i]) ? c : INFINITY;
        bs[i] = c < bs[i] ? c : bs[i];
    });
}

/* The window's sums at pixels [xa, xb) into least (the least where the gate allows; a NaN sum never). */
static void least_sums(double *restrict least, const struct inner *w, int64_t xa, int64_t xb) {
    if (xb <= xa) return;
    double *restrict ls = least + xa;
    const uint8_t *restrict al = w->al ? w->al + xa : NULL;
    WINDOW_SUMS(w, xa, xb, {
        const double u = (!al || al[i]) ? t : INFINITY;
        ls[i] = u < ls[i] ? u : ls[i];
    });
}

/* One chunk of rows of _min_window_costs_kernel. */
static int mwc_chunk(void *ctx, int64_t chunk) {
    const struct mwc_args *a = ctx;
    const int64_t H = a->v.H, W = a->v.W, S = a->S, K = a->K, G = a->G;
    int64_t up = 0, down = 0;
    for (int64_t k = 0; k < K; k++) {
        up = max64(up, -a->rects[k * 4 + 0]);
        down = max64(down, a->rects[k * 4 + 1]);
    }
    const int64_t R = up + down + 2;
    const int per_pixel = a->aH > 1 || a->aW > 1;
    const int64_t c0 = chunk * H / a->n_chunks;
    const int64_t c1 = (chunk + 1) * H / a->n_chunks;
    double *rings = malloc(sizeof(double) * G * R * S * W);
    float *acc = malloc(sizeof(float) * N_BLOCKS * W);
    float *rv = malloc(sizeof(float) * 2 * W);
    double *sums = malloc(sizeof(double) * S * SET_TILE);
    const float **rows_of = malloc(sizeof(float *) * S * N_BLOCKS);
    int64_t *count = malloc(sizeof(int64_t) * S);
    double *all_cols = malloc(sizeof(double) * G * K * W);
    double *best = malloc(sizeof(double) * W);
    double *least = malloc(sizeof(double) * W);
    struct inner *live = malloc(sizeof(struct inner) * (size_t)max64(K, 1));
    int status = 0;
    if (!rings || !acc || !rv || !sums || !all_cols || !best || !rows_of || !count || !least || !live) {
        status = -1;
        goto done;
    }
    for (int64_t s = 0; s < S; s++) { /* set_sum's rows: after set_from's blocks, or all of the set's */
        const int64_t *bs = a->set_blocks + s * N_BLOCKS;
        int64_t t = 0;
        const int64_t p = a->set_from[s];
        if (p >= 0)
            while (t < N_BLOCKS && a->set_blocks[p * N_BLOCKS + t] >= 0) t++;
        count[s] = 0;
        for (int64_t j = t; j < N_BLOCKS && (j == t || bs[j] >= 0); j++)
            rows_of[s * N_BLOCKS + count[s]++] = acc + bs[j] * W;
    }
    int ordered = 0; /* a negative count: the windows' costs taken window by window (below) */
    for (int64_t k = 0; k < K; k++) ordered |= a->counts[k] < 0.0;
    int64_t nxt = max64(c0 - up, 0);
    for (int64_t y = c0; y < c1; y++) {
        while (nxt <= min64(y + down, H - 1)) {
            for (int64_t g = 0; g < G; g++) {
                memset(acc, 0, sizeof(float) * N_BLOCKS * W);
                for (int64_t k = 0; k < a->v.n;) k = block_view_row(&a->v, a->disparities[g], nxt, acc, rv, k);
                fixed_set_rows(rows_of, a->set_from, count, a->set_order, S, W, sums,
                               rings + (g * R + nxt % R) * S * W);
            }
            nxt++;
        }
        for (int64_t g = 0; g < G; g++) {
            const double *ring = rings + g * R * S * W;
            double *cols = all_cols + g * K * W;
            for (int64_t x = 0; x < W; x++) best[x] = 1e300;
            int64_t n_live = 0;
            for (int64_t k = 0; k < K; k++) {
                const uint8_t *allowed_k = a->allowed + k * a->aH * a->aW;
                if (!per_pixel && !allowed_k[0]) continue;
                const int64_t s = a->window_set[k];
                const int64_t *rk = a->rects + k * 4;
                const int64_t ya = max64(y + rk[0], 0);
                const int64_t yb = min64(y + rk[1], H - 1) + 1;
                double *restrict col = cols + k * W;
                if (y == c0) {
                    const double *f = ring + ((ya % R) * S + s) * W;
                    for (int64_t x = 0; x < W; x++) col[x] = f[x];
                    for (int64_t r = ya + 1; r < yb; r++) {
                        f = ring + ((r % R) * S + s) * W;
                        for (int64_t x = 0; x < W; x++) col[x] += f[x];
                    }
                } else {
                    const int gone = y + rk[0] - 1 >= 0;
                    const int come = y + rk[1] <= H - 1;
                    const double *restrict f = ring + ((((y + rk[0] - 1) % R + R) % R) * S + s) * W;
                    const double *restrict h = ring + (((y + rk[1]) % R) * S + s) * W;
                    if (gone && come) {
                        for (int64_t x = 0; x < W; x++) col[x] += h[x] - f[x];
                    } else if (gone) {
                        for (int64_t x = 0; x < W; x++) col[x] -= f[x];
                    } else if (come) {
                        for (int64_t x = 0; x < W; x++) col[x] += h[x];
                    }
                }
                const double ck = a->counts[k];
                const int64_t ra = rk[2], rb = rk[3];
                const int64_t lo = min64(max64(-ra, 0), W);
                const int64_t hi = min64(max64(W - 1 - rb, lo), W);
                const uint8_t *al_row = per_pixel ? allowed_k + y * a->aW : NULL;
                for (int64_t e = 0; e < lo + W - hi; e++) {
                    const int64_t x = e < lo ? e : hi + e - lo;
                    if (per_pixel && !al_row[x]) continue;
                    const int64_t xa = max64(x + ra, 0);
                    const int64_t xb = min64(x + rb, W - 1) + 1;
                    double total = 0.0;
                    for (int64_t j = xa; j < xb; j++) total += col[j];
                    double c = total * FIXED_INV / ((double)((yb - ya) * (xb - xa)) * ck);
                    if (c < best[x]) best[x] = c;
                }
                /* the pixels whose window lies within the row: below, with the windows of the same
                 * denominator, or here where a count is negative */
                struct inner *w = &live[n_live++];
                w->col = col;
                w->al = per_pixel ? al_row : NULL;
                w->ra = ra;
                w->width = rb - ra + 1;
                w->lo = lo;
                w->hi = hi;
                w->denom = (double)((yb - ya) * (rb - ra + 1)) * ck;
                w->done = ordered;
                if (ordered) window_costs(best, w, lo, hi);
            }
            /* A window's cost is its sum times FIXED_INV (exact, a power of 2) over its denominator,
             * rounded once: rounding keeps the order of the exact values, so among windows of one
             * positive finite denominator (the same bits) the least sum gives the least cost, and a
             * pixel's least over all windows is the same whichever way it is taken (a NaN cost never
             * taken, none -0: the sums are >= +0). The windows of one denominator take their least
             * sum over the pixels all of them cover and divide once there (backgammon: 11 windows, 4
             * denominators, 0.300 -> 0.284 s on one thread); each window alone divides for its
             * other pixels, and a window of another denominator (0, inf or NaN counts) for all of
             * its. A negative count makes costs of -0, whose order counts: then every window goes
             * alone, in turn (above). */
            for (int64_t i = 0; i < n_live; i++) {
                if (live[i].done) continue;
                if (!(live[i].denom > 0.0 && live[i].denom < INFINITY)) { /* no order kept: each alone */
                    window_costs(best, &live[i], live[i].lo, live[i].hi);
                    continue;
                }
                int64_t from = live[i].lo, to = live[i].hi;
                for (int64_t j = i; j < n_live; j++) {
                    if (!same_bits(live[j].denom, live[i].denom)) continue;
                    from = max64(from, live[j].lo);
                    to = min64(to, live[j].hi);
                }
                to = max64(to, from);
                for (int64_t x = from; x < to; x++) least[x] = INFINITY;
                for (int64_t j = i; j < n_live; j++) {
                    const struct inner *v = &live[j];
                    if (!same_bits(v->denom, live[i].denom)) continue;
                    live[j].done = 1;
                    window_costs(best, v, v->lo, min64(from, v->hi));
                    window_costs(best, v, max64(to, v->lo), v->hi);
                    least_sums(least, v, from, to);
                }
                const double denom = live[i].denom;
                for (int64_t x = from; x < to; x++) {
                    const double c = least[x] * FIXED_INV / denom;
                    best[x] = c < best[x] ? c : best[x];
                }
            }
            float *out = a->out + (g * H + y) * W;
            for (int64_t x = 0; x < W; x++) out[x] = (float)best[x];
        }
    }
done:
    free(rings);
    free(acc);
    free(rv);
    free(sums);
    free(rows_of);
    free(count);
    free(all_cols);
    free(best);
    free(least);
    free(live);
    return status;
}

/* _min_window_costs_kernel: each of the G candidates' least window cost per pixel into out
 * (G, H, W) float32; the rows dealt out in n_chunks chunks to `threads` threads. allowed: (K, aH,
 * aW) uint8 (numpy bool), aH = aW = 1 for every pixel alike. */
int lfrig_min_window_costs(const float *gray, int64_t U, int64_t V, int64_t H, int64_t W, const int64_t *vu,
                           const int64_t *vv, const float *vdu, const float *vdv, const int64_t *vblock, int64_t n,
                           const float *disparities, int64_t G, const int64_t *set_blocks, const int64_t *set_from,
                           const int64_t *set_order, int64_t S, const int64_t *window_set, const int64_t *rects,
                           int64_t K, const double *counts, const uint8_t *allowed, int64_t aH, int64_t aW,
                           int64_t n_chunks, int64_t threads, float *out) {
    struct mwc_args a = {{gray, U, V, H, W, vu, vv, vblock, vdu, vdv, n}, disparities, G, set_blocks, set_from,
                         set_order, S, window_set, rects, K, counts, allowed, aH, aW, n_chunks, out};
    return run_items(mwc_chunk, &a, n_chunks, threads);
}

struct argmin_args {
    const float *costs;
    const double *candidates;
    double step;
    int64_t D, H, W;
    float *disparity, *best_out;
};

/* One row of _subpixel_argmin_kernel. */
static int argmin_row(void *ctx, int64_t y) {
    const struct argmin_args *a = ctx;
    const int64_t D = a->D, H = a->H, W = a->W;
    int64_t *kk = calloc((size_t)W, sizeof(int64_t));
    float *best = malloc(sizeof(float) * W);
    uint8_t *nan = calloc((size_t)W, 1);
    if (!kk || !best || !nan) {
        free(kk);
        free(best);
        free(nan);
        return -1;
    }
    const float *c0row = a->costs + y * W;
    for (int64_t x = 0; x < W; x++) {
        best[x] = c0row[x];
        nan[x] = c0row[x] != c0row[x];
    }
    for (int64_t d = 1; d < D; d++) {
        const float *row = a->costs + (d * H + y) * W;
        for (int64_t x = 0; x < W; x++) {
            float c = row[x];
            if (nan[x]) continue;
            if (c != c) {
                nan[x] = 1;
                kk[x] = d;
                best[x] = c;
            } else if (c < best[x]) {
                best[x] = c;
                kk[x] = d;
            }
        }
    }
    for (int64_t x = 0; x < W; x++) {
        int64_t k = kk[x];
        double c0 = (double)a->costs[(k * H + y) * W + x];
        double cm = (double)a->costs[(max64(k - 1, 0) * H + y) * W + x];
        double cp = (double)a->costs[(min64(k + 1, D - 1) * H + y) * W + x];
        double denom = cm - 2 * c0 + cp;
        double offset = 0.0;
        if (k > 0 && k < D - 1 && denom > 0) offset = 0.5 * (cm - cp) / denom;
        if (offset < -0.5)
            offset = -0.5;
        else if (offset > 0.5)
            offset = 0.5;
        a->disparity[y * W + x] = (float)(a->candidates[k] + offset * a->step);
        a->best_out[y * W + x] = (float)c0;
    }
    free(kk);
    free(best);
    free(nan);
    return 0;
}

/* _subpixel_argmin_kernel: costs (D, H, W) float32, candidates (D,) float64. */
int lfrig_subpixel_argmin(const float *costs, int64_t D, int64_t H, int64_t W, const double *candidates, double step,
                          float *disparity, float *best_out, int64_t threads) {
    struct argmin_args a = {costs, candidates, step, D, H, W, disparity, best_out};
    return run_items(argmin_row, &a, H, threads);
}

struct ambiguity_args {
    const float *costs;
    float delta;
    int64_t D, H, W;
    int32_t *out;
};

/* One row of _cost_ambiguity_kernel. */
static int ambiguity_row(void *ctx, int64_t y) {
    const struct ambiguity_args *a = ctx;
    const int64_t D = a->D, H = a->H, W = a->W;
    float *best = malloc(sizeof(float) * W);
    if (!best) return -1;
    for (int64_t x = 0; x < W; x++) best[x] = a->costs[y * W + x];
    for (int64_t d = 1; d < D; d++) {
        const float *row = a->costs + (d * H + y) * W;
        for (int64_t x = 0; x < W; x++) {
            float c = row[x];
            if (c != c || c < best[x])
                if (best[x] == best[x]) best[x] = c;
        }
    }
    int32_t *out = a->out + y * W;
    for (int64_t x = 0; x < W; x++) {
        best[x] = best[x] + a->delta;
        out[x] = 0;
    }
    for (int64_t d = 0; d < D; d++) {
        const float *row = a->costs + (d * H + y) * W;
        for (int64_t x = 0; x < W; x++)
            if (row[x] <= best[x]) out[x] += 1;
    }
    free(best);
    return 0;
}

/* _cost_ambiguity_kernel: costs (D, H, W) float32 into out (H, W) int32. */
int lfrig_cost_ambiguity(const float *costs, int64_t D, int64_t H, int64_t W, float delta, int32_t *out,
                         int64_t threads) {
    struct ambiguity_args a = {costs, delta, D, H, W, out};
    return run_items(ambiguity_row, &a, H, threads);
}

struct downsample_args {
    const float *gray;
    int64_t H, W, V, h, w, factor;
    float *out;
};

/* One row of blocks of one view of _downsample_kernel (item k = (u * V + v) * h + y). */
static int downsample_row(void *ctx, int64_t k) {
    const struct downsample_args *a = ctx;
    const int64_t h = a->h, w = a->w, factor = a->factor;
    const int64_t view = k / h, y = k % h;
    const float *img = a->gray + view * a->H * a->W;
    const float count = (float)(factor * factor);
    float *out = a->out + (view * h + y) * w;
    for (int64_t x = 0; x < w; x++) {
        float acc = 0.0f;
        for (int64_t i = 0; i < factor; i++) {
            float row = 0.0f;
            const float *src = img + (y * factor + i) * a->W + x * factor;
            for (int64_t j = 0; j < factor; j++) row += src[j];
            acc += row;
        }
        out[x] = acc / count;
    }
    return 0;
}

/* _downsample_kernel: gray (U, V, H, W) float32 into out (U, V, h, w) float32. */
int lfrig_downsample(const float *gray, int64_t U, int64_t V, int64_t H, int64_t W, int64_t factor, float *out,
                     int64_t h, int64_t w, int64_t threads) {
    struct downsample_args a = {gray, H, W, V, h, w, factor, out};
    return run_items(downsample_row, &a, U * V * h, threads);
}
