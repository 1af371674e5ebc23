/* The occlusion test of the region map (Eq. 9-11) and the visibility-aware boundary decision of the
 * matching-entropy estimator, compiled ahead of time: each mirrors its numba twin operation for
 * operation on the same types (no fused multiply-add, no fast math), so it gives the same bits.
 *
 * - lfrig_occlusion: recon/entropy/regions.py, _occlusion_kernel (with _landing);
 * - lfrig_snap: recon/entropy/boundary.py, _snap_kernel (with _hidden and _bilinear, and numba's
 *   np.median: its quickselect, numba/np/arraymath.py _median_inner, _select_two, _select and
 *   _partition, whose swaps decide which of two equal values (0.0 and -0.0) and which NaN it gives).
 *
 * Arrays are C-contiguous; the comments of the numba twins say why each loop has its shape. Each
 * output element is computed by one item (a band of rows; a chunk of tested pixels) whatever thread
 * runs it, so the bits do not depend on the number of threads. Python's min(a, b) and max(a, b) of
 * floats keep a unless b is less (greater): min_py and max_py, which fmin and fmax are not (NaN,
 * -0.0). A value out of int64's range (NaN, inf) converts to INT64_MIN, x86's "integer indefinite",
 * as in numba (to_int64: cvttsd2si itself on x86-64, without C's undefined conversion). The layer
 * maxima and minima and the occlusion sums are selects, not branches, as numba's (which way they go
 * is as common as not at a depth edge).
 */
#include "rows.h"

#if defined(__x86_64__)
#include <emmintrin.h>

/* int(v) of a float64 as numba converts it on x86-64: cvttsd2si. */
static inline int64_t to_int64(double v) { return _mm_cvttsd_si64(_mm_set_sd(v)); }
#else
static inline int64_t to_int64(double v) {
    return (v >= -9223372036854775808.0 && v < 9223372036854775808.0) ? (int64_t)v : INT64_MIN;
}
#endif

/* Python's min(a, b) and max(a, b) of two floats, as numba lowers them. */
static inline double min_py(double a, double b) { return b < a ? b : a; }
static inline double max_py(double a, double b) { return b > a ? b : a; }

/* What every band of lfrig_occlusion reads, and where it writes. */
struct occlusion_args {
    const float *layers;
    int64_t H, W;
    const double *offsets;
    int64_t n_views;
    float gap;
    const int64_t *row_shift;
    int64_t band_rows, span;
    const int64_t *row_start, *runs;
    float *neg, *pos;
};

/* _landing, one coordinate: the row (column) where a pixel of row (column) y and layer value m lands
 * in a view du rows (dv columns) from the centre, rounded to a pixel. */
static inline int64_t landing(int64_t y, float m, double du) {
    return to_int64(floor((double)y - du * (double)m + 0.5));
}

/* One spot of a band's stretch of rows: its top and bottom layers, and the view whose pixels it
 * holds (together: one cache line for the three). */
struct spot {
    float top, bottom;
    int32_t view;
};

/* Where pixel (y, x) of layer value m lands in view (du, dv): its spot in the stretch of rows t0 to
 * t1 (W columns), or -1 where it lands outside. */
static inline int64_t spot_index(int64_t y, int64_t x, float m, double du, double dv, int64_t t0, int64_t t1,
                                 int64_t W) {
    const int64_t ly = landing(y, m, du), lx = landing(x, m, dv);
    return (t0 <= ly && ly < t1 && 0 <= lx && lx < W) ? (ly - t0) * W + lx : -1;
}

/* One band of rows of _occlusion_kernel: its pixels' top and bottom layers view by view, each
 * view's forward warp of the rows that land on those the band reads into the band's own stretch.
 * The band's own pixels' spots are kept from the warp for the test (the same landings). */
static int occlusion_band(void *ctx, int64_t b) {
    const struct occlusion_args *a = ctx;
    const int64_t H = a->H, W = a->W;
    const int64_t lo = b * a->band_rows, hi = min64((b + 1) * a->band_rows, H);
    const int64_t rows = hi - lo + a->span;
    if (rows < 0) return -1;  /* as numba refuses an array of negative rows */
    const int64_t *row_start = a->row_start, *runs = a->runs;
    int64_t n_own = 0;  /* the band's pixels */
    for (int64_t i = row_start[lo]; i < row_start[hi]; i++) n_own += runs[2 * i + 1] - runs[2 * i];
    const size_t cells = (size_t)rows * (size_t)W;
    struct spot *spots = malloc(sizeof(struct spot) * cells);
    int64_t *own = malloc(sizeof(int64_t) * (size_t)max64(n_own, 1));  /* the band's pixels' spots */
    if (!spots || !own) {
        free(spots);
        free(own);
        return -1;
    }
    for (size_t i = 0; i < cells; i++) spots[i].view = -1;
    const float *layers = a->layers;
    float *neg = a->neg, *pos = a->pos;
    const float gap = a->gap;
    for (int64_t k = 0; k < a->n_views; k++) {
        const double du = a->offsets[2 * k], dv = a->offsets[2 * k + 1];
        const int64_t sa = a->row_shift[2 * k], sc = a->row_shift[2 * k + 1];
        const int64_t t0 = max64(lo + sa, 0), t1 = min64(hi - 1 + sc, H - 1) + 1;  /* the rows the band reads */
        const int64_t s0 = max64(t0 - sc, 0), s1 = min64(t1 - 1 - sa, H - 1) + 1;  /* the rows that land there */
        const int32_t kk = (int32_t)k;
        int64_t j = 0;
        for (int64_t y = s0; y < s1; y++) {
            const int keep = lo <= y && y < hi;
            for (int64_t i = row_start[y]; i < row_start[y + 1]; i++) {
                for (int64_t x = runs[2 * i]; x < runs[2 * i + 1]; x++) {
                    const float m = layers[y * W + x];
                    const int64_t q = spot_index(y, x, m, du, dv, t0, t1, W);
                    if (keep) own[j++] = q;
                    if (q >= 0) {
                        struct spot *p = spots + q;
                        const int first = p->view != kk;  /* the first pixel of this view there */
                        p->view = kk;
                        /* maxss and minss, then a masked move: selects, not branches, as numba's */
                        const float t = p->top, d = p->bottom;
                        const float up = m > t ? m : t, down = m < d ? m : d;
                        p->top = first ? m : up;
                        p->bottom = first ? m : down;
                    }
                }
            }
        }
        j = 0;
        for (int64_t y = lo; y < hi; y++) {
            const int kept = s0 <= y && y < s1;  /* else a row the warp left out: its landings made here */
            for (int64_t i = row_start[y]; i < row_start[y + 1]; i++) {
                for (int64_t x = runs[2 * i]; x < runs[2 * i + 1]; x++) {
                    const float m = layers[y * W + x];
                    const int64_t q = kept ? own[j++] : spot_index(y, x, m, du, dv, t0, t1, W);
                    if (q >= 0) {
                        /* t - m > gap as m - t < -gap (negation is exact): the same test, which the
                         * compiler makes a select of m - t, not a branch */
                        const float below = m - spots[q].top, above = m - spots[q].bottom;
                        neg[y * W + x] += (below < -gap) ? below : 0.0f;
                        pos[y * W + x] += (above > gap) ? above : 0.0f;
                    }
                }
            }
        }
    }
    free(spots);
    free(own);
    return 0;
}

/* _occlusion_kernel: the sums neg and pos ((H, W) float32, added to) of the occlusion test of the
 * pixels runs[row_start[y]:row_start[y + 1]] ((x0, x1) int64) of each row y, in bands of band_rows
 * rows dealt to `threads` threads. layers (H, W) float32; offsets (n_views, 2) float64 (du, dv);
 * row_shift (n_views, 2) int64, the least and most rows a pixel lands from its own in each view;
 * row_start (H + 1,) int64. */
int lfrig_occlusion(const float *layers, int64_t H, int64_t W, const double *offsets, int64_t n_views, float gap,
                    const int64_t *row_shift, int64_t band_rows, const int64_t *row_start, const int64_t *runs,
                    float *neg, float *pos, int64_t threads) {
    if (H <= 0 || W <= 0 || n_views <= 0 || band_rows <= 0) return 0;
    int64_t span = row_shift[1] - row_shift[0];
    for (int64_t k = 1; k < n_views; k++) span = max64(span, row_shift[2 * k + 1] - row_shift[2 * k]);
    struct occlusion_args a = {layers, H, W, offsets, n_views, gap, row_shift, band_rows, span, row_start, runs,
                               neg, pos};
    return run_items(occlusion_band, &a, (H + band_rows - 1) / band_rows, threads);
}

/* _bilinear: image ((H, W) float32) at (y, x), the coordinates clamped to it, in float64. */
static inline double bilinear(const float *image, int64_t H, int64_t W, double y, double x) {
    y = min_py(max_py(y, 0.0), (double)H - 1.0);
    x = min_py(max_py(x, 0.0), (double)W - 1.0);
    const int64_t y0 = H > 1 ? min64(to_int64(floor(y)), H - 2) : 0;
    const int64_t x0 = W > 1 ? min64(to_int64(floor(x)), W - 2) : 0;
    const double fy = y - (double)y0;
    const double fx = x - (double)x0;
    const int64_t y1 = min64(y0 + 1, H - 1);
    const int64_t x1 = min64(x0 + 1, W - 1);
    const float *r0 = image + y0 * W, *r1 = image + y1 * W;
    return ((1.0 - fy) * ((1.0 - fx) * (double)r0[x0] + fx * (double)r0[x1])
            + fy * ((1.0 - fx) * (double)r1[x0] + fx * (double)r1[x1]));
}

/* _hidden: whether an occluder of occ ((H, W) float32) hides pixel (y, x) at disparity d in view
 * (du, dv): its ray marched in steps of half a pixel while one could still be near enough. */
static inline int hidden(const float *occ, int64_t H, int64_t W, int64_t y, int64_t x, int64_t du, int64_t dv,
                         double d, float nearest, double landing_px, int64_t reach) {
    const int64_t ad = du < 0 ? -du : du, av = dv < 0 ? -dv : dv;
    const double a = (double)(av > ad ? av : ad);
    const double ds = 0.5 / a;
    const double tol = landing_px / a;
    const double bound = min_py((double)nearest - d + tol + ds, (double)reach / a);
    for (int64_t k = 1; (double)k * ds <= bound; k++) {
        const double s = (double)k * ds;
        const int64_t qy = to_int64(floor((double)y + (double)du * s + 0.5));
        const int64_t qx = to_int64(floor((double)x + (double)dv * s + 0.5));
        if (qy < 0 || qy >= H || qx < 0 || qx >= W) return 0;
        if (!(qy == y && qx == x) && (double)occ[qy * W + qx] > d + s - tol) return 1;
    }
    return 0;
}

static inline void swap(double *A, int64_t i, int64_t j) {
    const double t = A[i];
    A[i] = A[j];
    A[j] = t;
}

/* numba's _partition (pivot the median of low, middle and high): A[low:high + 1] split about the
 * pivot, whose place it returns. */
static int64_t partition(double *A, int64_t low, int64_t high) {
    const int64_t mid = (low + high) >> 1;
    if (A[mid] < A[low]) swap(A, low, mid);
    if (A[high] < A[mid]) swap(A, high, mid);
    if (A[mid] < A[low]) swap(A, low, mid);
    const double pivot = A[mid];
    swap(A, high, mid);
    int64_t i = low, j = high - 1;
    for (;;) {
        while (i < high && A[i] < pivot) i++;
        while (j >= low && pivot < A[j]) j--;
        if (i >= j) break;
        swap(A, i, j);
        i++;
        j--;
    }
    swap(A, i, high);
    return i;
}

/* numba's _select: the k'th smallest of A[low:high + 1]. */
static double select_kth(double *A, int64_t k, int64_t low, int64_t high) {
    int64_t i = partition(A, low, high);
    while (i != k) {
        if (i < k)
            low = i + 1;
        else
            high = i - 1;
        i = partition(A, low, high);
    }
    return A[k];
}

/* numba's np.median of A[:n] (n > 0; A is overwritten): _median_inner, with _select_two. */
static double median(double *A, int64_t n) {
    int64_t low = 0, high = n - 1;
    const int64_t half = n >> 1;
    if ((n & 1) != 0) return select_kth(A, half, low, high);
    const int64_t k = half - 1;
    for (;;) {
        const int64_t i = partition(A, low, high);
        if (i < k) {
            low = i + 1;
        } else if (i > k + 1) {
            high = i - 1;
        } else if (i == k) {
            select_kth(A, k + 1, i + 1, high);
            break;
        } else {
            select_kth(A, k, low, i - 1);
            break;
        }
    }
    return (A[k] + A[k + 1]) / 2.0;
}

/* What every tested pixel of lfrig_snap reads, and where it writes. */
struct snap_args {
    const float *gray;
    int64_t U, V, H, W;
    const float *m, *occ, *top;
    int64_t reach;
    const int64_t *ys, *xs;
    const double *far, *offsets;
    int64_t n_off;
    double landing_px;
    int64_t min_views;
    double threshold;
    double *far_mean, *near_mean;
    int64_t *views;
    double *far_median, *line;
    int64_t n;
};

/* One tested pixel of _snap_kernel; seen ((U, V) uint8) and samples ((U V,) float64): scratch. */
static void snap_pixel(const struct snap_args *a, int64_t i, uint8_t *restrict seen, double *restrict samples) {
    const int64_t U = a->U, V = a->V, H = a->H, W = a->W;
    const int64_t u0 = U / 2, v0 = V / 2;
    const int64_t y = a->ys[i], x = a->xs[i];
    const double df = a->far[i];
    const float nearest = a->top[y * W + x];  /* no occluder on any of its rays is nearer */
    const double dm = (double)a->m[y * W + x];
    const double centre = (double)a->gray[((u0 * V + v0) * H + y) * W + x];
    memset(seen, 0, (size_t)(U * V));
    int64_t n = 0, n_line = 0;
    double far_sum = 0.0, near0 = 0.0, far_line = 0.0, near_line0 = 0.0;
    for (int64_t u = 0; u < U; u++) {
        for (int64_t v = 0; v < V; v++) {
            const int64_t du = u - u0, dv = v - v0;
            if (du == 0 && dv == 0) continue;
            if (hidden(a->occ, H, W, y, x, du, dv, df, nearest, a->landing_px, a->reach)) continue;
            seen[u * V + v] = 1;
            const float *image = a->gray + (u * V + v) * H * W;
            const double sample = bilinear(image, H, W, (double)y - (double)du * df, (double)x - (double)dv * df);
            samples[n] = sample;
            n += 1;
            far_sum += fabs(sample - centre);
            const double e = fabs(bilinear(image, H, W, (double)y - (double)du * dm, (double)x - (double)dv * dm)
                                  - centre);
            near0 += e;
            if (du == 0 || dv == 0) {
                n_line += 1;
                far_line += fabs(sample - centre);
                near_line0 += e;
            }
        }
    }
    a->views[i] = n;
    a->far_mean[i] = far_sum / (double)max64(n, 1);
    a->far_median[i] = n > 0 ? median(samples, n) : NAN;  /* samples[:n] is the kernel's copy: not read again */
    double best = near0, best_line = near_line0;
    /* the other near offsets only where the far value already wins against m(p) itself */
    if (n >= a->min_views && (near0 - far_sum) / (double)n > a->threshold / sqrt((double)n)) {
        for (int64_t j = 1; j < a->n_off; j++) {
            const double d = dm + a->offsets[j];
            double s = 0.0, s_line = 0.0;
            for (int64_t u = 0; u < U; u++) {
                for (int64_t v = 0; v < V; v++) {
                    if (!seen[u * V + v]) continue;
                    const float *image = a->gray + (u * V + v) * H * W;
                    const double e = fabs(bilinear(image, H, W, (double)y - (double)(u - u0) * d,
                                                   (double)x - (double)(v - v0) * d) - centre);
                    s += e;
                    if (u == u0 || v == v0) s_line += e;
                }
            }
            if (s < best) best = s;
            if (s_line < best_line) best_line = s_line;
        }
    }
    a->near_mean[i] = best / (double)max64(n, 1);
    a->line[i] = n_line > 0 ? (best_line - far_line) / (double)n_line : NAN;
}

/* The tested pixels of a chunk of SNAP_CHUNK (threads write their outputs' cache lines apart). */
#define SNAP_CHUNK 64

static int snap_chunk(void *ctx, int64_t c) {
    const struct snap_args *a = ctx;
    uint8_t *seen = malloc((size_t)(a->U * a->V));
    double *samples = malloc(sizeof(double) * (size_t)(a->U * a->V));
    if (!seen || !samples) {
        free(seen);
        free(samples);
        return -1;
    }
    for (int64_t i = c * SNAP_CHUNK; i < min64((c + 1) * SNAP_CHUNK, a->n); i++) snap_pixel(a, i, seen, samples);
    free(seen);
    free(samples);
    return 0;
}

/* _snap_kernel: the view test's sums of the n tested pixels (ys, xs) ((n,) int64) with their far
 * values far ((n,) float64), dealt to `threads` threads. gray (U, V, H, W) float32; m, occ, top
 * (H, W) float32; offsets (n_off,) float64, the near offsets, 0 first; out: far_mean, near_mean,
 * far_median, line (n,) float64, views (n,) int64. */
int lfrig_snap(const float *gray, int64_t U, int64_t V, int64_t H, int64_t W, const float *m, const float *occ,
               const float *top, int64_t reach, const int64_t *ys, const int64_t *xs, const double *far, int64_t n,
               const double *offsets, int64_t n_off, double landing_px, int64_t min_views, double threshold,
               double *far_mean, double *near_mean, int64_t *views, double *far_median, double *line,
               int64_t threads) {
    if (n <= 0 || U <= 0 || V <= 0 || H <= 0 || W <= 0) return 0;
    struct snap_args a = {gray, U, V, H, W, m, occ, top, reach, ys, xs, far, offsets, n_off, landing_px, min_views,
                          threshold, far_mean, near_mean, views, far_median, line, n};
    return run_items(snap_chunk, &a, (n + SNAP_CHUNK - 1) / SNAP_CHUNK, threads);
}
