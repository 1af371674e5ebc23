/* The baseline's plane sweep (recon/costvolume.py, _sweep_kernel and the row helpers it calls),
 * compiled ahead of time: the same operations in the same order on the same types, so the same
 * bits. Each step below names the numba function it mirrors; the comments there say why each loop
 * has its shape. Built by recon/native/__init__.py with -ffp-contract=off (no fused multiply-add:
 * numba contracts none either) and without -ffast-math (the NaN test of the arg-min must stay).
 *
 * Arrays are C-contiguous: gray (U, V, H, W) float32; vu, vv (N,) int64 grid indices of the views;
 * oy, ox (D, N) int64 and fy, fx (D, N) float32, the shifts' integer parts and fractions;
 * edges (bands + 1,) int64; previous, best, c_minus, c_plus (H, W) float32; best_index (H, W) int64.
 */
#include "rows.h"

static inline int64_t reflect(int64_t i, int64_t n) {  /* _reflect */
    if (i < 0) return -i - 1;
    if (i >= n) return 2 * n - i - 1;
    return i;
}

/* _cost_rows: the summed absolute differences of row y for the D candidates into accs (D, W). */
static void cost_rows(const float *gray, int64_t U, int64_t V, int64_t H, int64_t W, const int64_t *vu,
                      const int64_t *vv, int64_t N, int64_t D, const int64_t *oy, const float *fy,
                      const int64_t *ox, const float *fx, int64_t y, float *accs, float *rv) {
    const int64_t plane = H * W;
    const float *c_row = gray + ((U / 2) * V + V / 2) * plane + y * W;
    memset(accs, 0, sizeof(float) * D * W);
    for (int64_t k = 0; k + 1 < N; k += 2) {
        const float *p_img = gray + (vu[k] * V + vv[k]) * plane;
        const float *q_img = gray + (vu[k + 1] * V + vv[k + 1]) * plane;
        for (int64_t j = 0; j < D; j++) {
            const float *p = view_row(p_img, H, W, y, oy[j * N + k], fy[j * N + k], rv);
            const float *q = view_row(q_img, H, W, y, oy[j * N + k + 1], fy[j * N + k + 1], rv + W);
            add_two_shifted_row_diffs(accs + j * W, c_row, W, p, ox[j * N + k], fx[j * N + k],
                                      q, ox[j * N + k + 1], fx[j * N + k + 1]);
        }
    }
    if (N % 2) {
        const float *img = gray + (vu[N - 1] * V + vv[N - 1]) * plane;
        for (int64_t j = 0; j < D; j++) {
            const float *row = view_row(img, H, W, y, oy[j * N + N - 1], fy[j * N + N - 1], rv);
            add_shifted_row_diff(accs + j * W, c_row, row, W, ox[j * N + N - 1], fx[j * N + N - 1]);
        }
    }
}

/* _row_sums: acc[x] = sum of src[reflect(x + k)] for k = -r..r, in that order, from 0.0. */
static void row_sums(const float *restrict src, int64_t w, int64_t r, double *restrict acc) {
    for (int64_t x = 0; x < w; x++) acc[x] = 0.0;
    for (int64_t k = -r; k <= r; k++) {
        int64_t lo = min64(max64(-k, 0), w);
        int64_t hi = max64(min64(w - k, w), lo);
        for (int64_t x = 0; x < lo; x++) acc[x] += src[reflect(x + k, w)];
        const float *restrict b = src + lo + k;
        double *restrict a = acc + lo;
        for (int64_t i = 0; i < hi - lo; i++) a[i] += b[i];
        for (int64_t x = hi; x < w; x++) acc[x] += src[reflect(x + k, w)];
    }
}

/* What every thread of one lfrig_sweep call reads and writes. */
struct sweep_args {
    const float *gray;
    int64_t U, V, H, W;
    const int64_t *vu, *vv;
    int64_t N;
    const int64_t *oy, *ox;
    const float *fy, *fx;
    int64_t D, first, window;
    const int64_t *edges;
    int64_t bands;
    float *previous, *best, *c_minus, *c_plus;
    int64_t *best_index;
};

/* One band of rows of _sweep_kernel. Returns 0, or -1 when its scratch memory could not be had
 * (nothing of the band written). */
static int sweep_band(void *ctx, int64_t b) {
    const struct sweep_args *a = ctx;
    const int64_t H = a->H, W = a->W, D = a->D;
    const int64_t r = a->window / 2;
    const int64_t n = 2 * r + 1;
    const float inv = (float)(1.0 / (double)a->N);
    const double scale = 1.0 / (double)(a->window * a->window);
    const int64_t lo = a->edges[b], hi = a->edges[b + 1];
    const int64_t y_first = max64(lo - r, 0);
    const int64_t y_end = min64(hi + r, H);
    float *cost = malloc(sizeof(float) * W);
    double *ring = malloc(sizeof(double) * D * n * W);
    float *accs = malloc(sizeof(float) * D * W);
    float *rv = malloc(sizeof(float) * 2 * W);
    double *col = malloc(sizeof(double) * W);
    int status = 0;
    if (!cost || !ring || !accs || !rv || !col) {
        status = -1;
        goto done;
    }
    for (int64_t y = y_first; y < y_end; y++) {
        cost_rows(a->gray, a->U, a->V, H, W, a->vu, a->vv, a->N, D, a->oy, a->fy, a->ox, a->fx, y, accs, rv);
        for (int64_t j = 0; j < D; j++) {
            const float *acc = accs + j * W;
            for (int64_t x = 0; x < W; x++) cost[x] = acc[x] * inv;
            row_sums(cost, W, r, ring + (j * n + y % n) * W);
        }
        /* the output rows whose window ends at row y (at the last row, the last r + 1 rows) */
        const int64_t out_lo = max64(y - r, lo);
        const int64_t out_hi = min64(y == H - 1 ? y + 1 : y - r + 1, hi);
        for (int64_t yo = out_lo; yo < out_hi; yo++) {
            for (int64_t j = 0; j < D; j++) {
                const int64_t index = a->first + j;
                for (int64_t x = 0; x < W; x++) col[x] = 0.0;
                for (int64_t k = -r; k <= r; k++) {
                    const double *restrict src = ring + (j * n + reflect(yo + k, H) % n) * W;
                    for (int64_t x = 0; x < W; x++) col[x] += src[x];
                }
                float *pr = a->previous + yo * W, *bs = a->best + yo * W;
                float *cm = a->c_minus + yo * W, *cp = a->c_plus + yo * W;
                int64_t *bi = a->best_index + yo * W;
                for (int64_t x = 0; x < W; x++) {
                    float c = (float)(col[x] * scale);
                    if (bi[x] == index - 1) cp[x] = c;
                    float m = bs[x];
                    if (index == 0 || c < m || (c != c && m == m)) {
                        bs[x] = c;
                        bi[x] = index;
                        cm[x] = pr[x];
                    }
                    pr[x] = c;
                }
            }
        }
    }
done:
    free(cost);
    free(ring);
    free(accs);
    free(rv);
    free(col);
    return status;
}

/* _sweep_kernel: candidates first .. first + D - 1 of the plane sweep, in bands of rows (edges) dealt
 * to `threads` threads, made for this call and joined before it returns: no pool outlives the call,
 * so a process may fork after it (an OpenMP pool does not survive a fork). Returns run_items'
 * status: 0, -1 when a band's scratch memory could not be had, -2 when a thread could not be
 * started. */
int lfrig_sweep(const float *gray, int64_t U, int64_t V, int64_t H, int64_t W, const int64_t *vu,
                const int64_t *vv, int64_t N, const int64_t *oy, const float *fy, const int64_t *ox,
                const float *fx, int64_t D, int64_t first, int64_t window, const int64_t *edges,
                int64_t bands, int64_t threads, float *previous, float *best, int64_t *best_index,
                float *c_minus, float *c_plus) {
    struct sweep_args a = {gray, U, V, H, W, vu, vv, N, oy, ox, fy, fx, D, first, window, edges, bands, previous,
                           best, c_minus, c_plus, best_index};
    return run_items(sweep_band, &a, bands, threads);
}
