/* The window selection of the matching-entropy estimator (recon/entropy/entropy.py, Eq. 1 and the
 * window choice of Section 4.2), compiled ahead of time so that it runs without numba: each function
 * mirrors its numba twin operation for operation on the same types (no fused multiply-add, no fast
 * math), so it gives the same bits.
 *
 * - lfrig_select: _select_kernel, with _add, _add_pixel, _window_entropy, _verdict, _ring_windows,
 *   _clear_ring and _clipped_windows.
 *
 * Arrays are C-contiguous; the comments of the numba twins say why each loop has its shape. The
 * pixels' bins are uint16 or uint32 (select_windows picks 16 bits where the histograms allow): each
 * function takes `wide` (0: uint16, 1: uint32), a constant in each of the two row functions that
 * inline them, so that each has its own loads; and the window functions take `occl` (whether the
 * pixel is in an occlusion region: its windows count mismatched pixels, else they test the layers)
 * as a constant in each of their calls, so that their pixel loops test neither.
 *
 * A pixel's bins are two here, its grey and its disparity bin, read in one load (4 bytes, or 8 when
 * wide); its mismatched-grey bin is the grey one plus n_grey + n_disp (the numba twin reads it from
 * a third column that select_windows fills so). A window's pixel loop indexes the bins, labels and
 * layers from their addresses at the window's base pixel by the ring's offsets: no multiply or add
 * per pixel beyond the load's own.
 *
 * A window's grey and disparity sums go as the two lanes of one SSE2 vector (struct pair): each
 * lane's additions are the scalar ones, in the same order, and each lane's two terms come from one
 * 16-byte load of xlogx[c], xlogx[c + 1] (two loads a pixel instead of four). Without SSE2 (or built
 * with -U__SSE2__, as the tests build it) the two sums are two doubles.
 */
#include "rows.h"
#ifdef __SSE2__
#include <emmintrin.h>
#endif

#define ALWAYS static inline __attribute__((always_inline))

/* Python's floor division of int64 (numba's //). */
static inline int64_t floordiv64(int64_t a, int64_t b) {
    int64_t q = a / b;
    return (a % b != 0 && ((a < 0) != (b < 0))) ? q - 1 : q;
}

/* Pixel q's grey bin (*g) and disparity bin (*d): bins' two of q (uint16 or uint32), in one load. */
ALWAYS void bins_at(const void *bins, int wide, uint64_t q, uint32_t *g, uint32_t *d) {
    if (wide) {
        uint64_t v;
        memcpy(&v, (const uint32_t *)bins + 2u * q, sizeof v);
        *g = (uint32_t)v;
        *d = (uint32_t)(v >> 32);
    } else {
        uint32_t v;
        memcpy(&v, (const uint16_t *)bins + 2u * q, sizeof v);
        *g = v & 0xffffu;
        *d = v >> 16;
    }
}

/* What every pixel's windows of a call read, and where they write. */
struct select_args {
    const void *bins;
    const uint8_t *labels;
    int64_t H, W;
    const int64_t *rects;
    int64_t n_shapes, n_sizes;
    const int64_t *sizes_n;
    double alpha1, a2_occl, a2_other;
    int64_t n_hist;
    uint32_t mismatched; /* n_grey + n_disp: a pixel's mismatched-grey bin less its grey bin */
    const double *xlogx;
    const int64_t *side_radius;
    const float *layers;
    double gap;
    const int64_t *max_size;
    const int64_t *order;
    int64_t margin;
    const uint64_t *ring;
    int64_t ring_len;
    const int64_t *ring_end;
    const uint8_t *paired;
    int64_t *shape_map, *size_map;
    float *best_e, *all_e;
    int dense;
    float *row_values;
    int64_t row_first;
    int64_t *counts;
    uint8_t *mask;
    const double *log_n;
};

/* A window's grey sum (lane 0, pair_g) and disparity sum (lane 1, pair_d). */
#ifdef __SSE2__
typedef __m128d pair;
ALWAYS double pair_g(pair v) { return _mm_cvtsd_f64(v); }
ALWAYS double pair_d(pair v) { return _mm_cvtsd_f64(_mm_unpackhi_pd(v, v)); }
#else
typedef struct {
    double g, d;
} pair;
ALWAYS double pair_g(pair v) { return v.g; }
ALWAYS double pair_d(pair v) { return v.d; }
#endif

/* One window's running sums (_add_pixel's sg and sd in gd, sm, m, mixed). */
struct sums {
    pair gd;
    double sm;
    int64_t m;
    int mixed;
};

/* Where a window's pixels are: bins, labels and layers from the window's base pixel on. */
struct base {
    const void *bins;
    const uint8_t *labels;
    const float *layers;
};

/* What _add_pixel reads besides the pixel: the pixel's region and layer. */
struct centre {
    int occl;
    int64_t opposite;
    float m_centre;
    int64_t cap, side_r;
    double a2;
};

/* _add: counts[k] += 1 and s + xlogx[c + 1] - xlogx[c] (c: the count before). */
ALWAYS double add(uint32_t *restrict counts, uint32_t k, double s, const double *restrict xlogx) {
    uint32_t c = counts[k];
    counts[k] = c + 1u;
    return s + xlogx[c + 1u] - xlogx[c];
}

/* _add_pixel: pixel q (flat index from the base pixel at p) into one window's histograms and sums. */
ALWAYS void add_pixel(const struct select_args *a, int wide, int occl, const struct base *p, uint64_t q,
                      uint32_t *restrict hist, struct sums *w, const struct centre *c) {
    uint32_t g, d;
    bins_at(p->bins, wide, q, &g, &d);
    /* _add of the grey bin g and of the disparity bin d (another bin: d >= n_grey > g) */
    const uint32_t cg = hist[g], cd = hist[d];
    hist[g] = cg + 1u;
    hist[d] = cd + 1u;
#ifdef __SSE2__
    const __m128d xg = _mm_loadu_pd(a->xlogx + cg), xd = _mm_loadu_pd(a->xlogx + cd);
    w->gd = _mm_sub_pd(_mm_add_pd(w->gd, _mm_unpackhi_pd(xg, xd)), _mm_unpacklo_pd(xg, xd));
#else
    w->gd.g = w->gd.g + a->xlogx[cg + 1u] - a->xlogx[cg];
    w->gd.d = w->gd.d + a->xlogx[cd + 1u] - a->xlogx[cd];
#endif
    if (occl) {
        if ((int64_t)p->labels[q] == c->opposite) {
            w->sm = add(hist, g + a->mismatched, w->sm, a->xlogx);
            w->m += 1;
        }
    } else if (a->gap >= 0 && fabsf(p->layers[q] - c->m_centre) > a->gap) {
        w->mixed = 1;
    }
}

/* The histograms of pixel q (from p) back to 0. */
ALWAYS void clear_pixel(const struct select_args *a, int wide, const struct base *p, uint64_t q,
                        uint32_t *restrict hist) {
    uint32_t g, d;
    bins_at(p->bins, wide, q, &g, &d);
    hist[g] = 0;
    hist[d] = 0;
    hist[g + a->mismatched] = 0;
}

/* _window_entropy: Eq. 1 from a window's pixel count n (logn: its log) and running sums. */
ALWAYS double window_entropy(int64_t n, double logn, const struct sums *w, double alpha1, double a2) {
    double e = (logn - pair_g(w->gd) / (double)n) + alpha1 * (pair_d(w->gd) / (double)n - logn);
    if (w->m > 0) e += a2 * (w->sm / (double)n - (double)w->m / (double)n * logn);
    return e;
}

/* _verdict: 2 window (s, size k) offered, 1 not at this size, 0 neither at this nor a larger size. */
ALWAYS int verdict(int occl, int64_t s, int64_t k, int64_t size, int64_t cap, int64_t side_r, int mixed) {
    if (occl) return 2;
    if (s == 0 && k > 0 && (size > cap || mixed)) return 0;
    if (s > 0 && mixed) return 0;
    if (s > 0 && floordiv64(size - 1, 2) < side_r) return 1;
    return 2;
}

/* _clear_ring: the histograms of a window of n ring pixels back to 0. */
ALWAYS void clear_ring(const struct select_args *a, int wide, uint32_t *restrict hist, const uint64_t *restrict ring,
                       int64_t n, const struct base *p) {
    if (a->n_hist <= 6 * n) {
        memset(hist, 0, sizeof(uint32_t) * (size_t)a->n_hist);
    } else {
        for (uint64_t i = 0; i < (uint64_t)n; i++) clear_pixel(a, wide, p, ring[i], hist);
    }
}

/* _ring_windows: the windows of shape s (and, if two, of shape s + 1) of a pixel that no window
 * of which the image clips, size by size along the rings: e_k[j * n_sizes + k], offered[j *
 * n_sizes + k] for shape s + j; then the histograms cleared. */
ALWAYS void ring_windows(const struct select_args *a, int wide, int occl, int two, int64_t s,
                         const uint64_t *restrict ring_a, const uint64_t *restrict ring_b,
                         const int64_t *restrict ends, const struct base *p,
                         uint32_t *restrict hist_a, uint32_t *restrict hist_b, const struct centre *c,
                         double *restrict e_k, uint8_t *restrict offered) {
    const int64_t n_sizes = a->n_sizes;
    struct sums wa = {{0.0, 0.0}, 0.0, 0, 0};
    struct sums wb = {{0.0, 0.0}, 0.0, 0, 0};
    int act_a = 1;
    int act_b = two;
    int64_t na = 0, nb = 0, n = 0;
    for (int64_t k = 0; k < n_sizes; k++) {
        uint64_t i0 = (uint64_t)n;
        n = ends[k];
        uint64_t i1 = (uint64_t)n;
        if (act_a && act_b) {
            for (uint64_t i = i0; i < i1; i++) {
                add_pixel(a, wide, occl, p, ring_a[i], hist_a, &wa, c);
                add_pixel(a, wide, occl, p, ring_b[i], hist_b, &wb, c);
            }
        } else if (act_a) {
            for (uint64_t i = i0; i < i1; i++) add_pixel(a, wide, occl, p, ring_a[i], hist_a, &wa, c);
        } else if (act_b) {
            for (uint64_t i = i0; i < i1; i++) add_pixel(a, wide, occl, p, ring_b[i], hist_b, &wb, c);
        }
        offered[k] = offered[n_sizes + k] = 0;
        if (act_a) {
            na = n;
            int v = verdict(occl, s, k, a->sizes_n[k], c->cap, c->side_r, wa.mixed);
            act_a = v > 0;
            if (v == 2) {
                offered[k] = 1;
                e_k[k] = window_entropy(n, a->log_n[n], &wa, a->alpha1, c->a2);
            }
        }
        if (act_b) {
            nb = n;
            int v = verdict(occl, s + 1, k, a->sizes_n[k], c->cap, c->side_r, wb.mixed);
            act_b = v > 0;
            if (v == 2) {
                offered[n_sizes + k] = 1;
                e_k[n_sizes + k] = window_entropy(n, a->log_n[n], &wb, a->alpha1, c->a2);
            }
        }
    }
    clear_ring(a, wide, hist_a, ring_a, na, p);
    if (two) clear_ring(a, wide, hist_b, ring_b, nb, p);
}

/* _clipped_windows: the windows of shape s of a pixel near the border, clipped to the image, each
 * size's new pixels in ring_order's order (so the sums of ring_windows bit for bit); then the
 * histograms cleared. */
ALWAYS void clipped_windows(const struct select_args *a, int wide, int occl, int64_t y, int64_t x, int64_t s,
                            uint32_t *restrict hist, const struct centre *c, double *restrict e_k,
                            uint8_t *restrict offered) {
    const int64_t n_sizes = a->n_sizes, H = a->H, W = a->W;
    const int64_t *rects_s = a->rects + s * n_sizes * 4;
    const struct base p = {a->bins, a->labels, a->layers};
    struct sums w = {{0.0, 0.0}, 0.0, 0, 0};
    int64_t n = 0;
    int64_t py0 = 0, px0 = 0, py1 = -1, px1 = -1;
    for (int64_t k = 0; k < n_sizes; k++) {
        const int64_t ya = max64(y + rects_s[k * 4 + 0], 0);
        const int64_t yb = min64(y + rects_s[k * 4 + 1], H - 1);
        const int64_t xa = max64(x + rects_s[k * 4 + 2], 0);
        const int64_t xb = min64(x + rects_s[k * 4 + 3], W - 1);
        for (int64_t yy = ya; yy < yb + 1; yy++) {
            int64_t runs[2][2];
            if (py0 <= yy && yy <= py1) {
                runs[0][0] = xa;
                runs[0][1] = min64(px0, xb + 1);
                runs[1][0] = max64(px1 + 1, xa);
                runs[1][1] = xb + 1;
            } else {
                runs[0][0] = xa;
                runs[0][1] = xb + 1;
                runs[1][0] = 0;
                runs[1][1] = 0;
            }
            for (int r = 0; r < 2; r++) {
                for (int64_t xx = runs[r][0]; xx < runs[r][1]; xx++) {
                    add_pixel(a, wide, occl, &p, (uint64_t)(yy * W + xx), hist, &w, c);
                    n += 1;
                }
            }
        }
        py0 = ya;
        py1 = yb;
        px0 = xa;
        px1 = xb;
        offered[k] = 0;
        int v = verdict(occl, s, k, a->sizes_n[k], c->cap, c->side_r, w.mixed);
        if (v == 0) {
            for (int64_t kk = k + 1; kk < n_sizes; kk++) offered[kk] = 0;
            break;
        }
        if (v == 2) {
            offered[k] = 1;
            e_k[k] = window_entropy(n, a->log_n[n], &w, a->alpha1, c->a2);
        }
    }
    for (int64_t yy = py0; yy < py1 + 1; yy++) {
        for (int64_t xx = px0; xx < px1 + 1; xx++) clear_pixel(a, wide, &p, (uint64_t)(yy * W + xx), hist);
    }
}

/* One row (order[jr]) of _select_kernel. */
ALWAYS int select_row(const struct select_args *a, int wide, int64_t jr) {
    const int64_t H = a->H, W = a->W, n_shapes = a->n_shapes, n_sizes = a->n_sizes;
    const int64_t r_max = floordiv64(a->sizes_n[n_sizes - 1] - 1, 2);
    const int64_t K = n_shapes * n_sizes;
    const int64_t ring_shift = r_max * W + r_max;
    const int64_t nb = (K + 7) / 8;
    const int64_t margin = a->margin;
    const int64_t y = a->order[jr];
    int64_t row_n = (y - a->row_first) * W * K;
    uint32_t *hist_a = calloc((size_t)a->n_hist, sizeof(uint32_t));
    uint32_t *hist_b = calloc((size_t)a->n_hist, sizeof(uint32_t));
    double *e_k = malloc(sizeof(double) * 2 * (size_t)n_sizes);
    uint8_t *offered = calloc(2 * (size_t)n_sizes, 1);
    if (!hist_a || !hist_b || !e_k || !offered) {
        free(hist_a);
        free(hist_b);
        free(e_k);
        free(offered);
        return -1;
    }
    for (int64_t x = 0; x < W; x++) {
        const int64_t p = y * W + x;
        const uint8_t lab = a->labels[p];
        struct centre c;
        c.occl = lab == 0 || lab == 1;
        c.opposite = lab == 0 ? 1 : 0;
        c.a2 = c.occl ? a->a2_occl : a->a2_other;
        const int64_t s_last = (c.occl || a->side_radius[p] <= r_max) ? n_shapes : 1;
        const int inside = margin <= y && y < H - margin && margin <= x && x < W - margin;
        const uint64_t base_u = (uint64_t)(p - ring_shift); /* the windows' base pixel, where inside */
        c.m_centre = a->layers[p];
        c.cap = a->max_size[p];
        c.side_r = a->side_radius[p];
        double best = -1e300;
        int64_t best_shape = 0;
        int64_t best_size = 0;
        int64_t s = c.occl ? 1 : 0;
        while (s < s_last) {
            const int two = inside && a->paired[s] && s + 1 < s_last;
            if (inside) {
                const struct base at = {(const char *)a->bins + base_u * (wide ? 8u : 4u), a->labels + base_u,
                                        a->layers + base_u};
                const uint64_t *ring_a = a->ring + s * a->ring_len;
                const uint64_t *ring_b = two ? ring_a + a->ring_len : ring_a;
                const int64_t *ends = a->ring_end + s * n_sizes;
                if (c.occl)
                    ring_windows(a, wide, 1, two, s, ring_a, ring_b, ends, &at, hist_a, hist_b, &c, e_k, offered);
                else
                    ring_windows(a, wide, 0, two, s, ring_a, ring_b, ends, &at, hist_a, hist_b, &c, e_k, offered);
            } else {
                clipped_windows(a, wide, c.occl, y, x, s, hist_a, &c, e_k, offered);
            }
            for (int64_t j = 0; j < (two ? 2 : 1); j++) {
                for (int64_t k = 0; k < n_sizes; k++) {
                    if (!offered[j * n_sizes + k]) continue;
                    const double e = e_k[j * n_sizes + k];
                    const int64_t kk = (s + j) * n_sizes + k;
                    if (a->dense) a->all_e[p * K + kk] = (float)e;
                    a->row_values[row_n] = (float)e;
                    row_n += 1;
                    a->counts[p] += 1;
                    a->mask[p * nb + (kk >> 3)] |= (uint8_t)(0x80 >> (kk & 7));
                    if (e > best + 1e-9 || (fabs(e - best) <= 1e-9 && a->sizes_n[k] > best_size)) {
                        best = e;
                        best_shape = s + j;
                        best_size = a->sizes_n[k];
                    }
                }
            }
            s += two ? 2 : 1;
        }
        a->shape_map[p] = best_shape;
        a->size_map[p] = best_size;
        a->best_e[p] = (float)best;
    }
    free(hist_a);
    free(hist_b);
    free(e_k);
    free(offered);
    return 0;
}

static int select_row16(void *ctx, int64_t jr) { return select_row(ctx, 0, jr); }

static int select_row32(void *ctx, int64_t jr) { return select_row(ctx, 1, jr); }

/* _select_kernel: the windows of the rows `order` (n_order of them, dealt to `threads` threads)
 * and their matching entropies. bins (H * W * 2,) uint16 (wide 0) or uint32 (wide 1), each pixel's
 * grey bin and its disparity bin (+ n_grey), the mismatched-grey bin being grey + n_grey + n_disp; labels
 * (H, W) uint8; rects (n_shapes, n_sizes, 4); sizes_n (n_sizes,); xlogx (n_xlogx,); side_radius,
 * max_size (H, W) int64; layers (H, W) float32; ring (n_shapes, ring_len) uint64; ring_end
 * (n_shapes, n_sizes); paired (n_shapes,) uint8 (numpy bool); shape_map, size_map (H, W) int64;
 * best_e (H, W) float32; all_e (H, W, K) float32 if dense; row_values the band's rows of W * K
 * float32 from row row_first on; counts (H * W,) int64; mask (H, W, (K + 7) / 8) uint8. */
int lfrig_select(const void *bins, int64_t wide, const uint8_t *labels, int64_t H, int64_t W, const int64_t *rects,
                 int64_t n_shapes, int64_t n_sizes, const int64_t *sizes_n, double alpha1, double a2_occl,
                 double a2_other, int64_t n_grey, int64_t n_disp, const double *xlogx, int64_t n_xlogx,
                 const int64_t *side_radius, const float *layers, double gap, const int64_t *max_size,
                 const int64_t *order, int64_t n_order, int64_t margin, const uint64_t *ring, int64_t ring_len,
                 const int64_t *ring_end, const uint8_t *paired, int64_t *shape_map, int64_t *size_map, float *best_e,
                 float *all_e, int64_t dense, float *row_values, int64_t row_first, int64_t *counts, uint8_t *mask,
                 int64_t threads) {
    if (n_order <= 0 || W <= 0 || n_sizes <= 0 || n_xlogx <= 0) return 0;
    double *log_n = malloc(sizeof(double) * (size_t)n_xlogx);
    if (!log_n) return -1;
    log_n[0] = 0.0;
    for (int64_t n = 1; n < n_xlogx; n++) log_n[n] = log((double)n);
    struct select_args a = {bins, labels, H, W, rects, n_shapes, n_sizes, sizes_n, alpha1, a2_occl, a2_other,
                            2 * n_grey + n_disp, (uint32_t)(n_grey + n_disp), xlogx, side_radius, layers, gap,
                            max_size, order, margin, ring, ring_len, ring_end, paired, shape_map, size_map, best_e,
                            all_e, dense != 0, row_values, row_first, counts, mask, log_n};
    int status = run_items(wide ? select_row32 : select_row16, &a, n_order, threads);
    free(log_n);
    return status;
}
