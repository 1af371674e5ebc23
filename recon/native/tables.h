/* The block rows and set rows of the matching-entropy estimator's cost (recon/entropy/cost.py),
 * shared by its kernels (initial.c, joint.c): each mirrors the numba function it names, the same
 * operations on the same types in the same order. */
#ifndef LFRIG_TABLES_H
#define LFRIG_TABLES_H

#include "rows.h"

#define N_BLOCKS 9
#define FIXED_POINT 268435456.0 /* 2^28: recon.entropy.cost.FIXED_POINT */
#define FIXED_INV (1.0 / FIXED_POINT)

/* cost.py _view_row's source rows a, b of the view's row at the float64 row sy and their weights gy, fy. */
static inline void view_rows_at(const float *img, int64_t H, int64_t W, double sy, const float **a, const float **b,
                                float *gy, float *fy) {
    if (sy < 0.0)
        sy = 0.0;
    else if (sy > H - 1.0)
        sy = H - 1.0;
    int64_t y0 = (int64_t)floor(sy);
    if (y0 > H - 2) y0 = H - 2;
    if (y0 < 0) y0 = 0;
    *fy = (float)(sy - (double)y0);
    *gy = 1.0f - *fy;
    int64_t y1 = min64(y0 + 1, H - 1);
    *a = img + y0 * W;
    *b = img + y1 * W;
}

/* cost.py _view_row: the view's row at the float64 row sy, blended from its two source rows. */
static void view_row_at(const float *img, int64_t H, int64_t W, double sy, float *restrict rv) {
    const float *a0, *b0;
    float gy, fy;
    view_rows_at(img, H, W, sy, &a0, &b0, &gy, &fy);
    const float *restrict a = a0;
    const float *restrict b = b0;
    for (int64_t x = 0; x < W; x++) rv[x] = gy * a[x] + fy * b[x];
}

#ifdef __AVX512F__
#include <immintrin.h>

/* A view's row as view_row_at blends it, read where it is needed instead of written first. */
struct blend {
    const float *a, *b;
    float gy, fy;
};

/* The blended row at x. */
static inline float blended(const struct blend *r, int64_t x) { return r->gy * r->a[x] + r->fy * r->b[x]; }

/* sample on the blended row. */
static inline float sample_blended(const struct blend *r, int64_t W, int64_t x, int64_t ox, float fx) {
    int64_t i = x + ox;
    if (i < 0) return blended(r, 0);
    if (i >= W - 1) return blended(r, W - 1);
    return (1.0f - fx) * blended(r, i) + fx * blended(r, i + 1);
}

/* The first c of 16 lanes. */
static inline __mmask16 first16(int64_t c) { return c >= 16 ? 0xffff : c <= 0 ? 0 : (__mmask16)((1u << c) - 1); }

/* The blended row at x .. x + 15, the lanes m of them (the others 0). */
static inline __m512 blended16(const struct blend *r, __m512 gy, __m512 fy, int64_t x, __mmask16 m) {
    if (!m) return _mm512_setzero_ps();
    return _mm512_add_ps(_mm512_mul_ps(gy, _mm512_maskz_loadu_ps(m, r->a + x)),
                         _mm512_mul_ps(fy, _mm512_maskz_loadu_ps(m, r->b + x)));
}

/* put_two_shifted_row_diffs of the views' blended rows p and q, each blended as it is read: 16 values of a
 * row at a time, the value after each one (fx's) from the next 16 (the same values as view_row_at's rows,
 * without writing and reading them back). */
static inline void put_two_blended_row_diffs(float *restrict acc, const float *restrict c_row, int64_t W,
                                             const struct blend *p, int64_t ox_p, float fx_p, const struct blend *q,
                                             int64_t ox_q, float fx_q, int fresh) {
    float gp = 1.0f - fx_p;
    float gq = 1.0f - fx_q;
    int64_t lo = min64(max64(max64(-ox_p, -ox_q), 0), W);
    int64_t hi = min64(max64(min64(W - 1 - ox_p, W - 1 - ox_q), lo), W);
    for (int64_t x = 0; x < lo; x++)
        acc[x] = ((fresh ? 0.0f : acc[x]) + fabsf(c_row[x] - sample_blended(p, W, x, ox_p, fx_p))) +
                 fabsf(c_row[x] - sample_blended(q, W, x, ox_q, fx_q));
    const int64_t n = hi - lo, ep = lo + ox_p, eq = lo + ox_q; /* the pixels' values at ep + i, eq + i, and i + 1 */
    const __m512 gyp = _mm512_set1_ps(p->gy), fyp = _mm512_set1_ps(p->fy);
    const __m512 gyq = _mm512_set1_ps(q->gy), fyq = _mm512_set1_ps(q->fy);
    const __m512 vgp = _mm512_set1_ps(gp), vfp = _mm512_set1_ps(fx_p);
    const __m512 vgq = _mm512_set1_ps(gq), vfq = _mm512_set1_ps(fx_q);
    /* (with n > 0 the values read, at ep .. ep + n and eq .. eq + n, lie in the row) */
    __m512 cp = blended16(p, gyp, fyp, ep, n > 0 ? first16(n + 1) : 0);
    __m512 cq = blended16(q, gyq, fyq, eq, n > 0 ? first16(n + 1) : 0);
    for (int64_t i = 0; i < n; i += 16) {
        const __mmask16 m = first16(n - i), next = first16(n + 1 - i - 16);
        const __m512 np = blended16(p, gyp, fyp, ep + i + 16, next), nq = blended16(q, gyq, fyq, eq + i + 16, next);
        const __m512 p1 = _mm512_castsi512_ps(_mm512_alignr_epi32(_mm512_castps_si512(np), _mm512_castps_si512(cp), 1));
        const __m512 q1 = _mm512_castsi512_ps(_mm512_alignr_epi32(_mm512_castps_si512(nq), _mm512_castps_si512(cq), 1));
        const __m512 c = _mm512_maskz_loadu_ps(m, c_row + lo + i);
        const __m512 vp = _mm512_add_ps(_mm512_mul_ps(vgp, cp), _mm512_mul_ps(vfp, p1));
        const __m512 vq = _mm512_add_ps(_mm512_mul_ps(vgq, cq), _mm512_mul_ps(vfq, q1));
        const __m512 dp = _mm512_abs_ps(_mm512_sub_ps(c, vp)), dq = _mm512_abs_ps(_mm512_sub_ps(c, vq));
        const __m512 old = fresh ? _mm512_setzero_ps() : _mm512_maskz_loadu_ps(m, acc + lo + i);
        _mm512_mask_storeu_ps(acc + lo + i, m, _mm512_add_ps(_mm512_add_ps(old, dp), dq));
        cp = np;
        cq = nq;
    }
    for (int64_t x = hi; x < W; x++)
        acc[x] = ((fresh ? 0.0f : acc[x]) + fabsf(c_row[x] - sample_blended(p, W, x, ox_p, fx_p))) +
                 fabsf(c_row[x] - sample_blended(q, W, x, ox_q, fx_q));
}
#endif

/* The views a cost reads (view_lists): gray (U, V, H, W) float32 and, per view, its grid index,
 * offsets from the centre view and block. */
struct views {
    const float *gray;
    int64_t U, V, H, W;
    const int64_t *vu, *vv, *vblock;
    const float *vdu, *vdv;
    int64_t n;
};

/* _block_view_rows for one row (acc (9, W) float32): view k's row added into its block's, with view
 * k + 1 in the same pass where it is in the same block; with `fresh` (k is its block's first view) onto
 * zeros that the block's row does not hold (put_shifted_row_diff). Returns the next view's index. */
static int64_t put_block_view_row(const struct views *v, float disparity, int64_t y, float *acc, float *rv, int64_t k,
                                  int fresh) {
    const int64_t H = v->H, W = v->W, plane = H * W;
    float base_p = -v->vdv[k] * disparity;
    float fl_p = floorf(base_p);
    int two = k + 1 < v->n && v->vblock[k + 1] == v->vblock[k];
    int64_t m = two ? k + 1 : k;
    float base_q = -v->vdv[m] * disparity;
    float fl_q = floorf(base_q);
    const float *centre = v->gray + ((v->U / 2) * v->V + v->V / 2) * plane + y * W;
    const float *img_p = v->gray + (v->vu[k] * v->V + v->vv[k]) * plane;
    float *row = acc + v->vblock[k] * W;
#ifdef __AVX512F__
    if (two) {
        struct blend p, q;
        view_rows_at(img_p, H, W, (double)y - (double)(v->vdu[k] * disparity), &p.a, &p.b, &p.gy, &p.fy);
        const float *img_q = v->gray + (v->vu[m] * v->V + v->vv[m]) * plane;
        view_rows_at(img_q, H, W, (double)y - (double)(v->vdu[m] * disparity), &q.a, &q.b, &q.gy, &q.fy);
        put_two_blended_row_diffs(row, centre, W, &p, (int64_t)fl_p, base_p - fl_p, &q, (int64_t)fl_q, base_q - fl_q,
                                  fresh);
        return m + 1;
    }
#endif
    view_row_at(img_p, H, W, (double)y - (double)(v->vdu[k] * disparity), rv);
    if (two) {
        const float *img_q = v->gray + (v->vu[m] * v->V + v->vv[m]) * plane;
        view_row_at(img_q, H, W, (double)y - (double)(v->vdu[m] * disparity), rv + W);
        put_two_shifted_row_diffs(row, centre, W, rv, (int64_t)fl_p, base_p - fl_p, rv + W, (int64_t)fl_q,
                                  base_q - fl_q, fresh);
    } else {
        put_shifted_row_diff(row, centre, rv, W, (int64_t)fl_p, base_p - fl_p, fresh);
    }
    return m + 1;
}

/* put_block_view_row onto the block's row as it is. */
static inline int64_t block_view_row(const struct views *v, float disparity, int64_t y, float *acc, float *rv,
                                     int64_t k) {
    return put_block_view_row(v, disparity, y, acc, rv, k, 0);
}

/* _set_sum: sums[s] = set s's row from the block rows (9, W), continuing set_from[s]'s sum. */
static double *set_sum(const float *rows, int64_t W, const int64_t *set_blocks, const int64_t *set_from, int64_t s,
                       double *sums) {
    double *restrict v = sums + s * W;
    int64_t t = 0;
    int64_t p = set_from[s];
    const int64_t *bs = set_blocks + s * N_BLOCKS;
    if (p >= 0) {
        const double *restrict before = sums + p * W;
        const int64_t *bp = set_blocks + p * N_BLOCKS;
        while (t < N_BLOCKS && bp[t] >= 0) t++;
        const float *restrict row_b = rows + bs[t] * W;
        for (int64_t x = 0; x < W; x++) v[x] = before[x] + (double)row_b[x];
    } else {
        const float *restrict row_b = rows + bs[0] * W;
        for (int64_t x = 0; x < W; x++) v[x] = (double)row_b[x];
    }
    t++;
    while (t < N_BLOCKS && bs[t] >= 0) {
        const float *restrict row_b = rows + bs[t] * W;
        for (int64_t x = 0; x < W; x++) v[x] += (double)row_b[x];
        t++;
    }
    return v;
}

#endif
