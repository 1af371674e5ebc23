/* Row helpers shared by the kernels of recon/native: each mirrors the numba function of the same
 * name in recon/costvolume.py (the same float32 operations in the same order), and a runner that
 * deals items to threads started and joined within one call (no pool outlives it: a process may
 * fork afterwards, which an OpenMP pool does not survive). */
#ifndef LFRIG_ROWS_H
#define LFRIG_ROWS_H

#include <math.h>
#include <pthread.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

static inline int64_t min64(int64_t a, int64_t b) { return a < b ? a : b; }
static inline int64_t max64(int64_t a, int64_t b) { return a > b ? a : b; }

/* _view_row: the view's row at y + oy + fy, blended into rv, or a source row itself. */
static inline const float *view_row(const float *img, int64_t H, int64_t W, int64_t y, int64_t oy, float fy,
                             float *restrict rv) {
    int64_t y0 = y + oy;
    if (y0 < 0) return img;
    if (y0 >= H - 1) return img + (H - 1) * W;
    if (fy == 0.0f) return img + y0 * W;
    const float *restrict a = img + y0 * W;
    const float *restrict b = a + W;
    float g = 1.0f - fy;
    for (int64_t x = 0; x < W; x++) rv[x] = g * a[x] + fy * b[x];
    return rv;
}

/* _sample */
static inline float sample(const float *row, int64_t W, int64_t x, int64_t ox, float fx) {
    int64_t i = x + ox;
    if (i < 0) return row[0];
    if (i >= W - 1) return row[W - 1];
    return (1.0f - fx) * row[i] + fx * row[i + 1];
}

/* add_shifted_row_diff; with `fresh` onto a row of zeros that acc does not hold (0 + each difference: the same
 * values as acc cleared first, without its clearing and its reads). */
static inline void put_shifted_row_diff(float *restrict acc, const float *restrict c_row, const float *restrict row,
                                        int64_t W, int64_t ox, float fx, int fresh) {
    float g = 1.0f - fx;
    int64_t lo = min64(max64(-ox, 0), W);
    int64_t hi = min64(max64(W - 1 - ox, lo), W);
    for (int64_t x = 0; x < lo; x++) acc[x] = (fresh ? 0.0f : acc[x]) + fabsf(c_row[x] - row[0]);
    const float *restrict r0 = row + lo + ox;
    const float *restrict r1 = row + lo + ox + 1;
    const float *restrict c = c_row + lo;
    float *restrict s = acc + lo;
    if (fresh)
        for (int64_t i = 0; i < hi - lo; i++) s[i] = 0.0f + fabsf(c[i] - (g * r0[i] + fx * r1[i]));
    else
        for (int64_t i = 0; i < hi - lo; i++) s[i] += fabsf(c[i] - (g * r0[i] + fx * r1[i]));
    for (int64_t x = hi; x < W; x++) acc[x] = (fresh ? 0.0f : acc[x]) + fabsf(c_row[x] - row[W - 1]);
}

/* add_shifted_row_diff */
static inline void add_shifted_row_diff(float *restrict acc, const float *restrict c_row, const float *restrict row,
                                 int64_t W, int64_t ox, float fx) {
    put_shifted_row_diff(acc, c_row, row, W, ox, fx, 0);
}

/* add_two_shifted_row_diffs; with `fresh` onto a row of zeros that acc does not hold (put_shifted_row_diff). */
static inline void put_two_shifted_row_diffs(float *restrict acc, const float *restrict c_row, int64_t W,
                                             const float *restrict p, int64_t ox_p, float fx_p,
                                             const float *restrict q, int64_t ox_q, float fx_q, int fresh) {
    float gp = 1.0f - fx_p;
    float gq = 1.0f - fx_q;
    int64_t lo = min64(max64(max64(-ox_p, -ox_q), 0), W);
    int64_t hi = min64(max64(min64(W - 1 - ox_p, W - 1 - ox_q), lo), W);
    for (int64_t x = 0; x < lo; x++)
        acc[x] = ((fresh ? 0.0f : acc[x]) + fabsf(c_row[x] - sample(p, W, x, ox_p, fx_p))) +
                 fabsf(c_row[x] - sample(q, W, x, ox_q, fx_q));
    const float *restrict p0 = p + lo + ox_p;
    const float *restrict p1 = p + lo + ox_p + 1;
    const float *restrict q0 = q + lo + ox_q;
    const float *restrict q1 = q + lo + ox_q + 1;
    const float *restrict c = c_row + lo;
    float *restrict s = acc + lo;
    if (fresh)
        for (int64_t i = 0; i < hi - lo; i++)
            s[i] = (0.0f + fabsf(c[i] - (gp * p0[i] + fx_p * p1[i]))) + fabsf(c[i] - (gq * q0[i] + fx_q * q1[i]));
    else
        for (int64_t i = 0; i < hi - lo; i++)
            s[i] = (s[i] + fabsf(c[i] - (gp * p0[i] + fx_p * p1[i]))) + fabsf(c[i] - (gq * q0[i] + fx_q * q1[i]));
    for (int64_t x = hi; x < W; x++)
        acc[x] = ((fresh ? 0.0f : acc[x]) + fabsf(c_row[x] - sample(p, W, x, ox_p, fx_p))) +
                 fabsf(c_row[x] - sample(q, W, x, ox_q, fx_q));
}

/* add_two_shifted_row_diffs */
static inline void add_two_shifted_row_diffs(float *restrict acc, const float *restrict c_row, int64_t W,
                                      const float *restrict p, int64_t ox_p, float fx_p,
                                      const float *restrict q, int64_t ox_q, float fx_q) {
    put_two_shifted_row_diffs(acc, c_row, W, p, ox_p, fx_p, q, ox_q, fx_q, 0);
}

/* What run_items calls for each item: 0, or nonzero when the item failed (its memory). */
typedef int (*item_fn)(void *ctx, int64_t item);

struct runner {
    item_fn fn;
    void *ctx;
    int64_t n, step, first;
    int failed;
    pthread_t id;
};

static void *runner_main(void *arg) {
    struct runner *r = arg;
    for (int64_t i = r->first; i < r->n; i += r->step)
        if (r->fn(r->ctx, i) != 0) r->failed = 1;
    return NULL;
}

/* fn(ctx, i) for i = 0 .. n - 1 on `threads` threads (this one among them), thread t taking items
 * t, t + threads, ... as numba's prange deals them to its threads when there are as many items as
 * threads. Returns 0, -1 when an item failed or no memory, -2 when a thread could not be started
 * (items of the threads not started are not done). */
static int run_items(item_fn fn, void *ctx, int64_t n, int64_t threads) {
    if (n <= 0) return 0;
    if (threads > n) threads = n;
    if (threads < 1) threads = 1;
    struct runner *pool = calloc((size_t)threads, sizeof(struct runner));
    if (!pool) return -1;
    int64_t started = 0;
    int status = 0;
    for (int64_t t = 1; t < threads; t++) {
        pool[t] = (struct runner){fn, ctx, n, threads, t, 0, 0};
        if (pthread_create(&pool[t].id, NULL, runner_main, &pool[t]) != 0) {
            status = -2;
            break;
        }
        started = t;
    }
    if (status == 0) {
        pool[0] = (struct runner){fn, ctx, n, threads, 0, 0, 0};
        runner_main(&pool[0]);
    }
    for (int64_t t = 1; t <= started; t++) pthread_join(pool[t].id, NULL);
    for (int64_t t = 0; t < threads && status == 0; t++)
        if (pool[t].failed) status = -1;
    free(pool);
    return status;
}

/* The threads of one call that work in step (run_crew): a gate they wait at until all are started
 * (or one could not be, when they leave), and a barrier between the stretches of their work. */
struct crew {
    pthread_mutex_t lock;
    pthread_cond_t cond;
    int64_t count, waiting, generation;
    int state; /* 0 until the threads are started, then 1 (go) or -1 (leave) */
};

static inline int crew_gate(struct crew *c) {
    pthread_mutex_lock(&c->lock);
    while (c->state == 0) pthread_cond_wait(&c->cond, &c->lock);
    const int go = c->state > 0;
    pthread_mutex_unlock(&c->lock);
    return go;
}

static inline void crew_open(struct crew *c, int state) {
    pthread_mutex_lock(&c->lock);
    c->state = state;
    pthread_cond_broadcast(&c->cond);
    pthread_mutex_unlock(&c->lock);
}

/* Wait until every thread of the crew is here. */
static inline void crew_barrier(struct crew *c) {
    if (c->count <= 1) return;
    pthread_mutex_lock(&c->lock);
    const int64_t generation = c->generation;
    if (++c->waiting == c->count) {
        c->waiting = 0;
        c->generation++;
        pthread_cond_broadcast(&c->cond);
    } else {
        while (generation == c->generation) pthread_cond_wait(&c->cond, &c->lock);
    }
    pthread_mutex_unlock(&c->lock);
}

/* What run_crew calls on each thread t of the crew c (c->count threads). */
typedef void (*crew_fn)(const void *args, struct crew *c, int64_t t);

struct crew_member {
    crew_fn fn;
    const void *args;
    struct crew *c;
    int64_t t;
    pthread_t id;
};

static inline void *crew_member_main(void *arg) {
    struct crew_member *m = arg;
    if (crew_gate(m->c)) m->fn(m->args, m->c, m->t);
    return NULL;
}

/* fn(args, crew, t) for t = 0 .. threads - 1 at once, each on a thread of its own (this one is t = 0),
 * started once for the call and joined before it returns; fn may wait at crew_barrier. No fn runs
 * until every thread is started. Returns 0, -1 for no memory, -2 when a thread could not be started
 * (then no fn runs). */
static inline int run_crew(crew_fn fn, const void *args, int64_t threads) {
    if (threads < 1) threads = 1;
    struct crew_member *team = calloc((size_t)threads, sizeof(struct crew_member));
    if (!team) return -1;
    struct crew c = {PTHREAD_MUTEX_INITIALIZER, PTHREAD_COND_INITIALIZER, threads, 0, 0, 0};
    int status = 0;
    int64_t started = 0;
    for (int64_t t = 1; t < threads; t++) {
        team[t] = (struct crew_member){fn, args, &c, t, 0};
        if (pthread_create(&team[t].id, NULL, crew_member_main, &team[t]) != 0) {
            status = -2;
            break;
        }
        started = t;
    }
    crew_open(&c, status == 0 ? 1 : -1);
    if (status == 0) fn(args, &c, 0);
    for (int64_t t = 1; t <= started; t++) pthread_join(team[t].id, NULL);
    free(team);
    return status;
}

#endif
