/* The block rows and set rows of the matching-entropy estimator's cost (recon/entropy/cost.py),
 * shared by its kernels (initial.c, joint.c): each mirrors the numba function it names, the same
 * operations on the same types in the same order. */
#ifndef LFRIG_TABLES_H
#define LFRIG_TABLES_H

#include "rows.h"

#define N_BLOCKS 9
#define FIXED_POINT 268435456.0 /* 2^28: recon.entropy.cost.FIXED_POINT */
#define FIXED_INV (1.0 / FIXED_POINT)

/* cost.py _view_row: the view's row at the float64 row sy, blended from its two source rows. */
static void view_row_at(const float *img, int64_t H, int64_t W, double sy, float *restrict rv) {
    if (sy < 0.0)
        sy = 0.0;
    else if (sy > H - 1.0)
        sy = H - 1.0;
    int64_t y0 = (int64_t)floor(sy);
    if (y0 > H - 2) y0 = H - 2;
    if (y0 < 0) y0 = 0;
    float fy = (float)(sy - (double)y0);
    float gy = 1.0f - fy;
    int64_t y1 = min64(y0 + 1, H - 1);
    const float *restrict a = img + y0 * W;
    const float *restrict b = img + y1 * W;
    for (int64_t x = 0; x < W; x++) rv[x] = gy * a[x] + fy * b[x];
}

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
    view_row_at(img_p, H, W, (double)y - (double)(v->vdu[k] * disparity), rv);
    float *row = acc + v->vblock[k] * W;
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
