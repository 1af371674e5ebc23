/* The kernels of the matching-entropy estimator's joint line search (Eq. 7, recon/entropy/matching.py
 * joint_line_search), compiled ahead of time: each mirrors its numba twin operation for operation
 * on the same types (no fused multiply-add, no fast math), so it gives the same bits.
 *
 * - lfrig_joint_group: recon/entropy/matching.py, _joint_group_kernel (with _joint_row and
 *   _joint_edge_pixel; recon/entropy/cost.py ring_table_rows, _fixed_table_row and
 *   compiled_window_reach; the block and set rows of tables.h);
 * - lfrig_offer_counts, lfrig_offer_runs: recon/entropy/layout.py, _offer_runs_kernel's two scans
 *   (with _offer_runs and _put_run).
 *
 * Arrays are C-contiguous; the comments of the numba twins say why each loop has its shape. The
 * summed-area tables are int64 sums that numba lets wrap; here they are added as uint64 (the same
 * bits, without C's undefined signed overflow). Where the CPU has AVX-512 the two innermost loops
 * (a run of pixels' objectives, a table row's running sum) are written with its intrinsics: the same
 * operations on the same values, eight pixels at a time, the last few under a mask (the compiler's
 * loop over a run takes 16 or 64 pixels at a time and leaves the rest, much of a short run, to a
 * scalar tail); elsewhere they are plain loops. Integer sums give the same bits in any order. A value
 * out of int64's range (NaN, inf) converts to INT64_MIN, x86's "integer indefinite", as in numba.
 */
#if defined(__AVX512F__) && defined(__GNUC__) && !defined(__clang__)
/* GCC's own loops here (the views' rows blended and their differences added, the set rows' sums: the
 * rows of tables.h and rows.h included below) in 512-bit vectors, not the 256 it prefers on this CPU,
 * element by element the same operations on the same values (backgammon's calls 5-8 % less CPU). */
#pragma GCC target("prefer-vector-width=512")
#endif

#include "tables.h"

#ifdef __AVX512F__
#include <immintrin.h>

/* The lanes of the 8 values from i of n. */
static inline __mmask8 lanes(int64_t i, int64_t n) { return n - i >= 8 ? 0xff : (__mmask8)((1u << (n - i)) - 1); }

/* The running sum of the 8 int64 lanes of v. */
static inline __m512i prefix8(__m512i v) {
    const __m512i z = _mm512_setzero_si512();
    v = _mm512_add_epi64(v, _mm512_alignr_epi64(v, z, 7));
    v = _mm512_add_epi64(v, _mm512_alignr_epi64(v, z, 6));
    return _mm512_add_epi64(v, _mm512_alignr_epi64(v, z, 4));
}
#endif

/* recon.entropy.cost: MAGIC_FLOAT, MAGIC_BITS, MAGIC_LIMIT and FIXED_LIMIT (2^51 / 2^28 - 1). */
#define MAGIC_FLOAT 6755399441055744.0
#define MAGIC_BITS UINT64_C(0x4338000000000000)
#define MAGIC_LIMIT (INT64_C(1) << 51)
#define FIXED_LIMIT 8388607.0

static inline int64_t wrap_sub(int64_t a, int64_t b) { return (int64_t)((uint64_t)a - (uint64_t)b); }

/* tables[ib, s, x1] - tables[ia, s, x1] - tables[ib, s, x0] + tables[ia, s, x0] (int64). */
static inline int64_t window_total(const int64_t *ta, const int64_t *tb, int64_t x0, int64_t x1) {
    return (int64_t)((((uint64_t)tb[x1] - (uint64_t)ta[x1]) - (uint64_t)tb[x0]) + (uint64_t)ta[x0]);
}

/* cost.py _fixed_table_row (first False): cur ((W + 1,) int64) = the row of v ((W,) float64) rounded
 * to multiples of 1 / FIXED_POINT, summed along x, onto prev. fixed: (W,) int64 scratch. */
static void fixed_table_row(const double *restrict v, int64_t W, int64_t *restrict fixed, const int64_t *restrict prev,
                            int64_t *restrict cur) {
#ifdef __AVX512F__
    {  /* the magic conversion and the sum in one pass; a row with a value out of range is made again below */
        const __m512d limit = _mm512_set1_pd(FIXED_LIMIT), point = _mm512_set1_pd(FIXED_POINT);
        const __m512d half = _mm512_set1_pd(0.5), magic = _mm512_set1_pd(MAGIC_FLOAT);
        const __m512i bits = _mm512_set1_epi64((int64_t)MAGIC_BITS), last = _mm512_set1_epi64(7);
        __m512i carry = _mm512_setzero_si512();
        __mmask8 out = 0;
        for (int64_t x = 0; x < W; x += 8) {
            const __mmask8 m = lanes(x, W);
            const __m512d f = _mm512_maskz_loadu_pd(m, v + x);
            out |= _mm512_mask_cmp_pd_mask(m, _mm512_abs_pd(f), limit, _CMP_NLT_UQ);
            const __m512d g = _mm512_add_pd(_mm512_floor_pd(_mm512_add_pd(_mm512_mul_pd(f, point), half)), magic);
            const __m512i run = prefix8(_mm512_sub_epi64(_mm512_castpd_si512(g), bits));
            const __m512i sum = _mm512_add_epi64(run, carry);
            carry = _mm512_add_epi64(carry, _mm512_permutexvar_epi64(last, run));
            _mm512_mask_storeu_epi64(cur + x + 1, m, _mm512_add_epi64(sum, _mm512_maskz_loadu_epi64(m, prev + x + 1)));
        }
        cur[0] = 0;
        if (!out) return;
    }
#endif
    int64_t out_of_range = 0;
    for (int64_t x = 0; x < W; x++) out_of_range += !(fabs(v[x]) < FIXED_LIMIT);
    if (out_of_range == 0) {
        for (int64_t x = 0; x < W; x++) {
            double f = floor(v[x] * FIXED_POINT + 0.5) + MAGIC_FLOAT;
            uint64_t bits;
            memcpy(&bits, &f, sizeof bits);
            fixed[x] = (int64_t)(bits - MAGIC_BITS);
        }
    } else {
        for (int64_t x = 0; x < W; x++) fixed[x] = (int64_t)floor(v[x] * FIXED_POINT + 0.5);
    }
    cur[0] = 0;
    uint64_t acc = 0;
    for (int64_t x = 0; x < W; x++) {
        acc += (uint64_t)fixed[x];
        cur[x + 1] = (int64_t)(acc + (uint64_t)prev[x + 1]);
    }
}

/* The sets of a joint search's tables (set_sums_plan). */
struct sets {
    const int64_t *blocks, *from, *order;
    int64_t S;
};

/* cost.py ring_table_rows, its block rows: rows y .. y + n - 1 of the block rows (n, 9, W) float32 of
 * m candidates, candidate i's at disparities[i * step] into acc + i * stride, view by view and, for
 * each view, candidate by candidate: a view's source rows, which the candidates' nearby disparities
 * mostly share, come from cache for all but the first (a stretch's rows of all the views, 1.6 MB on
 * backgammon, do not stay in cache from one candidate to the next). Each block row gets its views in
 * the same order as one candidate at a time. rv (2, W) float32: scratch. */
static void block_rows(const struct views *v, const float *disparities, int64_t step, int64_t m, int64_t y, int64_t n,
                       float *acc, int64_t stride, float *rv) {
    const int64_t W = v->W;
    /* a block's first view puts its differences onto zeros (put_block_view_row), and only the rows of a block
     * without views are cleared: acc, 2.2 MB a thread on backgammon, is not cleared and read back first */
    int started[N_BLOCKS] = {0};
    for (int64_t k = 0; k < v->n; k++) started[v->vblock[k]] = -1;
    for (int64_t b = 0; b < N_BLOCKS; b++)
        for (int64_t i = 0; i < m && !started[b]; i++)
            for (int64_t j = 0; j < n; j++) memset(acc + i * stride + (j * N_BLOCKS + b) * W, 0, sizeof(float) * W);
    for (int64_t k = 0; k < v->n;) { /* _block_rows */
        const int fresh = started[v->vblock[k]] < 0;
        int64_t next = k;
        for (int64_t i = 0; i < m; i++)
            for (int64_t j = 0; j < n; j++)
                next = put_block_view_row(v, disparities[i * step], y + j, acc + i * stride + j * N_BLOCKS * W, rv, k,
                                          fresh);
        started[v->vblock[k]] = 1;
        k = next;
    }
}

/* cost.py ring_table_rows, its set rows: rows y + 1 .. y + n of the sets' summed-area tables at one
 * candidate into the ring (R, S, W + 1) int64, table row r in slot r % R, made from the row above it,
 * from the block rows acc (n, 9, W) float32 of image rows y .. y + n - 1. sums (S, W) float64, fixed
 * (W,) int64: scratch. */
static void set_table_rows(const struct sets *p, int64_t W, int64_t y, int64_t n, const float *acc, int64_t *ring,
                           int64_t R, double *sums, int64_t *fixed) {
    const int64_t S = p->S, W1 = W + 1;
    for (int64_t j = 0; j < n; j++) {
        const int64_t *prev = ring + ((y + j) % R) * S * W1;
        int64_t *cur = ring + ((y + j + 1) % R) * S * W1;
        for (int64_t i = 0; i < S; i++) {
            const int64_t s = p->order[i];
            fixed_table_row(set_sum(acc + j * N_BLOCKS * W, W, p->blocks, p->from, s, sums), W, fixed, prev + s * W1,
                            cur + s * W1);
        }
    }
}

struct joint_args {
    struct views v;
    struct sets p;
    const float *disparities;
    int64_t G;
    const uint8_t *pixel_set;
    const int64_t *rects, *window_shape;
    int64_t K;
    const double *counts;
    const float *penalty;
    const int64_t *run_start;
    const int32_t *runs;
    double scale;
    int64_t rows, up, down, R, per_thread;
    float *out, *best;
    int64_t *best_k;
    /* the candidates' rings (G, R, S, W + 1) and k_best (2, G, rows, W) int32 (a window's index: K < 2^31,
     * half the bytes of int64 to store and fold); per thread, scratch (acc: the
     * block rows (per_thread, rows, 9, W) of the thread's candidates, a seventh of their rings) */
    int64_t *tables;
    int32_t *k_best;
    float *acc, *rv;
    double *sums, *c_best;
    int64_t *fixed, *ps64;
};

/* matching.py _joint_edge_pixel: the window at x clipped by the image's left or right edge. */
static inline void joint_edge_pixel(int64_t x, int64_t k, int64_t ya, int64_t yb, int64_t ra, int64_t rb, int64_t W,
                                    const int64_t *ta, const int64_t *tb, double cnt, double scale, const float *pen,
                                    int every, uint8_t want, const uint8_t *ps, double *c_best, int32_t *k_best) {
    const int64_t xa = max64(x + ra, 0);
    const int64_t xb = min64(x + rb, W - 1) + 1;
    const double total = (double)window_total(ta, tb, xa, xb) * FIXED_INV;
    const double c = scale * total / ((double)((yb - ya) * (xb - xa)) * cnt) + (double)pen[x];
    if ((every || ps[x] == want) && c < c_best[x]) {
        c_best[x] = c;
        k_best[x] = (int32_t)k;
    }
}

#ifdef __AVX512F__
/* joint_run_magic's pixels i .. i + 7 of its run, the lanes m of them (ps: the pixels' sets as bytes). */
static inline void joint_lanes_magic(const uint64_t *restrict a1, const uint64_t *restrict b1,
                                     const uint64_t *restrict a0, const uint64_t *restrict b0,
                                     const float *restrict pn, const uint8_t *restrict ps, int every, __m128i wanted,
                                     __m512d sc, __m512d dn, __m256i kv, double *restrict cb, int32_t *restrict kb,
                                     int64_t i, __mmask8 m) {
    const __m512i bits = _mm512_set1_epi64((int64_t)MAGIC_BITS);
    const __m512d magic = _mm512_set1_pd(MAGIC_FLOAT), inv = _mm512_set1_pd(FIXED_INV);
    __m512i t = _mm512_sub_epi64(_mm512_maskz_loadu_epi64(m, b1 + i), _mm512_maskz_loadu_epi64(m, a1 + i));
    t = _mm512_sub_epi64(t, _mm512_maskz_loadu_epi64(m, b0 + i));
    t = _mm512_add_epi64(_mm512_add_epi64(t, _mm512_maskz_loadu_epi64(m, a0 + i)), bits);
    const __m512d f = _mm512_sub_pd(_mm512_castsi512_pd(t), magic);
    const __m256 p = _mm256_maskz_loadu_ps(m, pn + i);
    const __m512d c = _mm512_add_pd(_mm512_div_pd(_mm512_mul_pd(sc, _mm512_mul_pd(f, inv)), dn), _mm512_cvtps_pd(p));
    const __mmask8 in = every ? m : (__mmask8)_mm_mask_cmpeq_epi8_mask(m, _mm_maskz_loadu_epi8(m, ps + i), wanted);
    /* c < old where the pass applies: elsewhere numba's c is inf, never below old (<= 1e300) */
    const __mmask8 less = _mm512_mask_cmp_pd_mask(in, c, _mm512_maskz_loadu_pd(m, cb + i), _CMP_LT_OQ);
    _mm512_mask_storeu_pd(cb + i, less, c);
    _mm256_mask_storeu_epi32(kb + i, less, kv);
}
#endif

/* _joint_row's loop over the pixels lo .. lo + n - 1 of a run, whose windows the image holds (a1, b1,
 * a0, b0: their windows' corners in the table rows ya and yb, from the right and left corners of lo's;
 * pn, ps, pv, cb, kb: the penalty, the pixels' sets as bytes and as int64 and c_best, k_best from lo), when every
 * window total is below MAGIC_LIMIT: its int64 -> float64 conversion as the bits of t + MAGIC_BITS, less
 * MAGIC_FLOAT. With AVX-512: whole vectors of eight pixels under a constant mask, then the last few
 * under theirs (a mask made for every vector of a run cost a fifth of the loop's instructions). */
static void joint_run_magic(const uint64_t *restrict a1, const uint64_t *restrict b1, const uint64_t *restrict a0,
                            const uint64_t *restrict b0, const float *restrict pn, const uint8_t *restrict ps,
                            const int64_t *restrict pv, int every, int64_t want, double scale, double denom,
                            int64_t k, int64_t n, double *restrict cb, int32_t *restrict kb) {
#ifdef __AVX512F__
    (void)pv;
    const __m128i wanted = _mm_set1_epi8((char)want);
    const __m256i kv = _mm256_set1_epi32((int32_t)k);
    const __m512d sc = _mm512_set1_pd(scale), dn = _mm512_set1_pd(denom);
    int64_t i = 0;
    for (; i + 8 <= n; i += 8) joint_lanes_magic(a1, b1, a0, b0, pn, ps, every, wanted, sc, dn, kv, cb, kb, i, 0xff);
    if (i < n) joint_lanes_magic(a1, b1, a0, b0, pn, ps, every, wanted, sc, dn, kv, cb, kb, i, lanes(i, n));
#else
    for (int64_t i = 0; i < n; i++) {
        const uint64_t bits = b1[i] - a1[i] - b0[i] + a0[i] + MAGIC_BITS;
        double f;
        memcpy(&f, &bits, sizeof f);
        f = f - MAGIC_FLOAT;
        double c = scale * (f * FIXED_INV) / denom + (double)pn[i];
        c = (every | (pv[i] == want)) ? c : INFINITY;
        const double old = cb[i];
        kb[i] = c < old ? (int32_t)k : kb[i];
        cb[i] = c < old ? c : old;
    }
#endif
}

/* joint_run_magic where a window total may reach MAGIC_LIMIT: the plain int64 -> float64 conversion (ps: the
 * pixels' sets as bytes). */
static void joint_run(const uint64_t *restrict a1, const uint64_t *restrict b1, const uint64_t *restrict a0,
                      const uint64_t *restrict b0, const float *restrict pn, const uint8_t *restrict ps, int every,
                      int64_t want, double scale, double denom, int64_t k, int64_t n, double *restrict cb,
                      int32_t *restrict kb) {
    for (int64_t i = 0; i < n; i++) {
        const double f = (double)(int64_t)(b1[i] - a1[i] - b0[i] + a0[i]);
        double c = scale * (f * FIXED_INV) / denom + (double)pn[i];
        c = (every | (ps[i] == want)) ? c : INFINITY;
        const double old = cb[i];
        kb[i] = c < old ? (int32_t)k : kb[i];
        cb[i] = c < old ? c : old;
    }
}

/* matching.py _joint_row: one candidate's objective at the pixels of row y, the least over the windows
 * (ascending, strict <) folded into c_best / k_best ((W,) float64 and int64). ring: the candidate's
 * table rows (R, S, W + 1); magic: every window total of the row is below MAGIC_LIMIT. ps64: (W,)
 * scratch, the row's pixel_set as int64. */
static void joint_row(const struct joint_args *a, const int64_t *ring, int64_t y, int magic, double *restrict c_best,
                      int32_t *restrict k_best, int64_t *restrict ps64) {
    const int64_t H = a->v.H, W = a->v.W, K = a->K, R = a->R, S = a->p.S, W1 = W + 1;
    const uint8_t *ps = a->pixel_set + y * W;
#ifndef __AVX512F__ /* (the vector loop compares the bytes) */
    for (int64_t x = 0; x < W; x++) ps64[x] = ps[x];
#endif
    for (int64_t k = 0; k < K; k++) {
        const int64_t *rk = a->rects + k * 4;
        const int64_t ya = max64(y + rk[0], 0);
        const int64_t yb = min64(y + rk[1], H - 1) + 1;
        const int64_t ia = ya % R, ib = yb % R;
        const int64_t ra = rk[2], rb = rk[3];
        const int64_t i0 = (y * K + k) * 2;
        const float *pen = a->penalty + (y * K + k) * W;
        for (int64_t r = a->run_start[i0]; r < a->run_start[i0 + 2]; r++) {
            const int64_t x0 = a->runs[r * 2], x1 = a->runs[r * 2 + 1];
            const int pas = r >= a->run_start[i0 + 1];
            const int64_t s = pas ? a->window_shape[k] : 0;
            const int every = a->window_shape[k] == 0;
            const uint8_t want = (uint8_t)pas;
            const double cnt = a->counts[s];
            const int64_t lo = min64(max64(x0, -ra), x1);
            const int64_t hi = max64(min64(x1, W - 1 - rb), lo);
            const int64_t n = hi - lo;
            const int64_t *ta = ring + (ia * S + s) * W1;
            const int64_t *tb = ring + (ib * S + s) * W1;
            for (int64_t x = x0; x < lo; x++)
                joint_edge_pixel(x, k, ya, yb, ra, rb, W, ta, tb, cnt, a->scale, pen, every, want, ps, c_best, k_best);
            if (n > 0) {
                const double denom = (double)((yb - ya) * (rb - ra + 1)) * cnt;
                const uint64_t *a1 = (const uint64_t *)ta + lo + rb + 1;
                const uint64_t *b1 = (const uint64_t *)tb + lo + rb + 1;
                const uint64_t *a0 = (const uint64_t *)ta + lo + ra;
                const uint64_t *b0 = (const uint64_t *)tb + lo + ra;
                if (magic)
                    joint_run_magic(a1, b1, a0, b0, pen + lo, ps + lo, ps64 + lo, every, pas, a->scale, denom, k,
                                    n, c_best + lo, k_best + lo);
                else
                    joint_run(a1, b1, a0, b0, pen + lo, ps + lo, every, pas, a->scale, denom, k, n, c_best + lo,
                              k_best + lo);
            }
            for (int64_t x = hi; x < x1; x++)
                joint_edge_pixel(x, k, ya, yb, ra, rb, W, ta, tb, cnt, a->scale, pen, every, want, ps, c_best, k_best);
        }
    }
}

/* The stretch of rows [y0, y1) of _joint_group_kernel: the tables hold the image rows before made,
 * the stretch needs those before need; its k_best is buffer `buffer` of two. */
struct stretch {
    int64_t y0, y1, made, need, buffer;
};

/* Candidate g's objectives at the stretch's rows into out, from its ring of table rows (thread t's
 * scratch). */
static void joint_candidate(const struct joint_args *a, const struct stretch *st, int64_t g, int64_t t) {
    const int64_t H = a->v.H, W = a->v.W, S = a->p.S, R = a->R, W1 = W + 1;
    const int64_t *ring = a->tables + g * R * S * W1;
    /* no window total of the stretch exceeds its rows' total (the set values are >= 0) */
    const int64_t *top = ring + (max64(st->y0 - a->up, 0) % R) * S * W1;
    const int64_t *bottom = ring + (st->need % R) * S * W1;
    int magic = 1;
    for (int64_t s = 0; s < S; s++) magic = magic && wrap_sub(bottom[s * W1 + W], top[s * W1 + W]) < MAGIC_LIMIT;
    double *cb = a->c_best + t * W;
    for (int64_t y = st->y0; y < st->y1; y++) {
        int32_t *kb = a->k_best + ((st->buffer * a->G + g) * a->rows + y - st->y0) * W;
        for (int64_t x = 0; x < W; x++) cb[x] = 1e300;
        for (int64_t x = 0; x < W; x++) kb[x] = -1;
        joint_row(a, ring, y, magic, cb, kb, a->ps64 + t * W);
        float *out = a->out + (g * H + y) * W;
        for (int64_t x = 0; x < W; x++) out[x] = (float)cb[x];
    }
}

/* The body of _joint_group_kernel's loop over the candidates for one stretch, for thread t of T's
 * candidates t, t + T, ...: each one's ring extended to the rows the stretch needs (ring_table_rows,
 * `rows` image rows at a time: the block rows of all of them, then each one's set rows), and, right
 * after its last set rows, while they are in cache, its objectives at the stretch's rows. */
static void joint_candidates(const struct joint_args *a, const struct stretch *st, int64_t t, int64_t T) {
    const int64_t W = a->v.W, S = a->p.S, R = a->R, W1 = W + 1;
    const int64_t m = t < a->G ? (a->G - t + T - 1) / T : 0, stride = a->rows * N_BLOCKS * W;
    float *acc = a->acc + t * a->per_thread * stride;
    for (int64_t y = st->made; y < st->need; y += a->rows) {
        const int64_t n = min64(a->rows, st->need - y);
        block_rows(&a->v, a->disparities + t, T, m, y, n, acc, stride, a->rv + t * 2 * W);
        for (int64_t i = 0; i < m; i++) {
            const int64_t g = t + i * T;
            set_table_rows(&a->p, W, y, n, acc + i * stride, a->tables + g * R * S * W1, R, a->sums + t * S * W,
                           a->fixed + t * W);
            if (y + n == st->need) joint_candidate(a, st, g, t);
        }
    }
    if (st->made >= st->need)
        for (int64_t i = 0; i < m; i++) joint_candidate(a, st, t + i * T, t);
}

/* The body of _joint_group_kernel's fold for row y0 + j of a stretch: each candidate's objective, in
 * order, into best / best_k where it is less (strict <: the first least wins). */
static void joint_fold(const struct joint_args *a, const struct stretch *st, int64_t j) {
    const int64_t H = a->v.H, W = a->v.W, y = st->y0 + j;
    float *restrict best = a->best + y * W;
    int64_t *restrict best_k = a->best_k + y * W;
    for (int64_t g = 0; g < a->G; g++) {
        const float *restrict out = a->out + (g * H + y) * W;
        const int32_t *restrict kb = a->k_best + ((st->buffer * a->G + g) * a->rows + j) * W;
        for (int64_t x = 0; x < W; x++) {
            const int less = out[x] < best[x];
            best_k[x] = less ? kb[x] : best_k[x];
            best[x] = less ? out[x] : best[x];
        }
    }
}

/* Thread t of T's share of _joint_group_kernel, stretch after stretch: candidates t, t + T, ...
 * (prange(G)), then, once every candidate has made the stretch, its rows t, t + T, ... (prange over
 * the rows). k_best has a buffer per stretch parity, so that the next stretch's candidates need not
 * wait for this one's fold; the barrier after them waits for it. */
static void joint_share(const struct joint_args *a, struct crew *c, int64_t t) {
    const int64_t H = a->v.H, T = c->count;
    struct stretch st = {0, 0, 0, 0, 0};
    for (int64_t y0 = 0; y0 < H; y0 += a->rows) {
        st.y0 = y0;
        st.y1 = min64(y0 + a->rows, H);
        st.need = min64(st.y1 + a->down, H);
        joint_candidates(a, &st, t, T);
        crew_barrier(c);
        for (int64_t j = t; j < st.y1 - y0; j += T) joint_fold(a, &st, j);
        st.made = st.need;
        st.buffer ^= 1;
    }
}

/* joint_share as run_crew calls it. */
static void joint_crew(const void *a, struct crew *c, int64_t t) { joint_share(a, c, t); }

static void *alloc(size_t bytes) { return malloc(bytes ? bytes : 1); }

/* _joint_group_kernel: the joint search for the G candidates disparities (G,) float32 into out (G, H,
 * W) float32, folded into best (H, W) float32 and best_k (H, W) int64; `rows` image rows at a time
 * (at least one). pixel_set (H, W) uint8 (numpy bool), rects (K, 4) and window_shape (K,) int64 (each
 * shape < S), counts (>= S,) float64, penalty (H, K, W) float32, run_start (H * K * 2 + 1,) int64
 * and runs (n, 2) int32 (offer_runs). On `threads` threads (at most G), started once for the call. */
int lfrig_joint_group(const float *gray, int64_t U, int64_t V, int64_t H, int64_t W, const int64_t *vu,
                      const int64_t *vv, const float *vdu, const float *vdv, const int64_t *vblock, int64_t n,
                      const float *disparities, int64_t G, const int64_t *set_blocks, const int64_t *set_from,
                      const int64_t *set_order, int64_t S, const uint8_t *pixel_set, const int64_t *rects,
                      const int64_t *window_shape, int64_t K, const double *counts, const float *penalty,
                      const int64_t *run_start, const int32_t *runs, double scale, int64_t rows, float *out,
                      float *best, int64_t *best_k, int64_t threads) {
    if (G <= 0 || H <= 0 || W <= 0) return 0;
    if (K > INT32_MAX) return -1; /* k_best's int32 (a penalty of 2^31 windows a pixel is more memory than there is) */
    if (rows < 1) rows = 1; /* (no value depends on it) */
    int64_t up = 0, down = 0; /* compiled_window_reach */
    for (int64_t k = 0; k < K; k++) {
        up = max64(up, -rects[k * 4 + 0]);
        down = max64(down, rects[k * 4 + 1]);
    }
    const int64_t R = rows + up + down + 1, W1 = W + 1;
    const int64_t T = max64(min64(threads, G), 1);
    struct joint_args a = {{gray, U, V, H, W, vu, vv, vblock, vdu, vdv, n}, {set_blocks, set_from, set_order, S},
                           disparities, G, pixel_set, rects, window_shape, K, counts, penalty, run_start, runs, scale,
                           rows, up, down, R};
    a.out = out;
    a.best = best;
    a.best_k = best_k;
    a.tables = alloc(sizeof(int64_t) * (size_t)(G * R * S * W1));
    a.k_best = alloc(sizeof(int32_t) * (size_t)(2 * G * rows * W));
    a.per_thread = (G + T - 1) / T;
    a.acc = alloc(sizeof(float) * (size_t)(T * a.per_thread * rows * N_BLOCKS * W));
    a.rv = alloc(sizeof(float) * (size_t)(T * 2 * W));
    a.sums = alloc(sizeof(double) * (size_t)(T * S * W));
    a.c_best = alloc(sizeof(double) * (size_t)(T * W));
    a.fixed = alloc(sizeof(int64_t) * (size_t)(T * W));
    a.ps64 = alloc(sizeof(int64_t) * (size_t)(T * W));
    int status = 0;
    if (!a.tables || !a.k_best || !a.acc || !a.rv || !a.sums || !a.c_best || !a.fixed || !a.ps64) {
        status = -1;
        goto done;
    }
    for (int64_t g = 0; g < G; g++) memset(a.tables + g * R * S * W1, 0, sizeof(int64_t) * (size_t)(S * W1));
    status = run_crew(joint_crew, &a, T);
done:
    free(a.tables);
    free(a.k_best);
    free(a.acc);
    free(a.rv);
    free(a.sums);
    free(a.c_best);
    free(a.fixed);
    free(a.ps64);
    return status;
}

/* layout.py _offer_runs (with _put_run): the runs of the pixels that offer one window in one row, both
 * passes in one scan, gaps below gap closed; n[p] advanced by each pass's runs, which are written to
 * runs unless it is NULL. */
static void offer_row(const float *row, const uint8_t *occluded, int shaped, int64_t W, int64_t gap, int32_t *runs,
                      int64_t *n) {
    int64_t lo[2] = {-1, -1}, hi[2] = {-1, -1};
    for (int64_t x = 0; x < W; x++) {
        if (row[x] == INFINITY) continue;
        const int p = shaped && occluded[x] ? 1 : 0;
        if (lo[p] >= 0 && x - hi[p] >= gap) {
            if (runs) {
                runs[n[p] * 2] = (int32_t)lo[p];
                runs[n[p] * 2 + 1] = (int32_t)hi[p];
            }
            n[p]++;
            lo[p] = -1;
        }
        if (lo[p] < 0) lo[p] = x;
        hi[p] = x + 1;
    }
    for (int p = 0; p < 2; p++) {
        if (lo[p] >= 0) {
            if (runs) {
                runs[n[p] * 2] = (int32_t)lo[p];
                runs[n[p] * 2 + 1] = (int32_t)hi[p];
            }
            n[p]++;
        }
    }
}

struct offer_args {
    const float *penalty;
    int64_t H, K, W;
    const uint8_t *pixel_set;
    const int64_t *window_shape;
    int64_t gap;
    int64_t *count;
    int32_t *runs;
};

/* One row of _offer_runs_kernel's first scan: the runs of each window and pass, counted. */
static int offer_count_row(void *ctx, int64_t y) {
    const struct offer_args *a = ctx;
    for (int64_t k = 0; k < a->K; k++) {
        int64_t n[2] = {0, 0};
        offer_row(a->penalty + (y * a->K + k) * a->W, a->pixel_set + y * a->W, a->window_shape[k] != 0, a->W, a->gap,
                  NULL, n);
        a->count[(y * a->K + k) * 2 + 1] = n[0];
        a->count[(y * a->K + k) * 2 + 2] = n[1];
    }
    return 0;
}

/* One row of _offer_runs_kernel's second scan: the runs written where the counts put them. */
static int offer_write_row(void *ctx, int64_t y) {
    const struct offer_args *a = ctx;
    for (int64_t k = 0; k < a->K; k++) {
        int64_t n[2] = {a->count[(y * a->K + k) * 2], a->count[(y * a->K + k) * 2 + 1]};
        offer_row(a->penalty + (y * a->K + k) * a->W, a->pixel_set + y * a->W, a->window_shape[k] != 0, a->W, a->gap,
                  a->runs, n);
    }
    return 0;
}

/* _offer_runs_kernel's first scan: count (H * K * 2 + 1,) int64, the start of each (row, window,
 * pass)'s runs and, last, their number. penalty (H, K, W) float32, pixel_set (H, W) uint8,
 * window_shape (K,) int64; gap: layout.RUN_GAP. */
int lfrig_offer_counts(const float *penalty, int64_t H, int64_t K, int64_t W, const uint8_t *pixel_set,
                       const int64_t *window_shape, int64_t gap, int64_t *count, int64_t threads) {
    struct offer_args a = {penalty, H, K, W, pixel_set, window_shape, gap, count, NULL};
    count[0] = 0;
    int status = run_items(offer_count_row, &a, H, threads);
    if (status != 0) return status;
    for (int64_t i = 0; i < H * K * 2; i++) count[i + 1] += count[i];
    return 0;
}

/* _offer_runs_kernel's second scan: runs (count[H * K * 2], 2) int32 from lfrig_offer_counts' count. */
int lfrig_offer_runs(const float *penalty, int64_t H, int64_t K, int64_t W, const uint8_t *pixel_set,
                     const int64_t *window_shape, int64_t gap, const int64_t *count, int32_t *runs, int64_t threads) {
    struct offer_args a = {penalty, H, K, W, pixel_set, window_shape, gap, (int64_t *)count, runs};
    return run_items(offer_write_row, &a, H, threads);
}
