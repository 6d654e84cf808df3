/*
 * usl_step.c -- a plain C reference of the MPM step that `skfem-mpm bench`
 * times, so that its throughput can be compared with the project's compiled
 * executor on the same problem in the same run.
 *
 * The step: update stress last (USL), lumped mass, quadratic B-splines on a
 * uniform grid with open (clamped) knot vectors, gravity as a grid
 * acceleration, fixed dofs, small-strain linear elasticity and the volume
 * update; 1D, 2D and 3D. With particles p, grid dofs i and N_ip = N_i(x_p):
 *
 *   m_i = sum_p m_p N_ip,   P_i = sum_p m_p v_p N_ip,
 *   f_i = -sum_p V_p sigma_p . grad N_i(x_p)
 *   a_i = f_i / m_i + g,    v_i = P_i / m_i + dt a_i   (free dofs with mass;
 *                                                       0 on fixed or empty)
 *   v_p += dt sum_i N_ip a_i,   x_p += dt sum_i N_ip v_i   (u_p likewise)
 *   L_p = sum_i v_i (x) grad N_i(x_p),   D = dt sym(L_p)
 *   sigma_p += lambda tr(D) I + 2 mu D     (1D: sigma_p += E dt L_p)
 *   V_p *= det(I + dt L_p)                 (3D: the rule of Sarrus)
 *
 * (Sulsky, Zhou & Schreyer 1995 for the update-stress-last step; the
 * project's skfem_mpm.solve.schemes.step_usl for the same sequence.)
 *
 * Threads (OpenMP): the particles are split into one contiguous block per
 * thread; each thread scatters its block into its own copy of the grid and
 * records the node range it touched; the grid update sums the copies over
 * those ranges. No two threads write the same memory, so the scatter needs
 * no atomics and the sums do not depend on scheduling.
 *
 * Usage:  usl_step INPUT OUTPUT [REPEAT]
 *
 * INPUT (native byte order, written by skfem_mpm.reference_c):
 *   char    magic[8]      "USLSTEP2"
 *   int64   dim, cells_x, cells_y, cells_z (1 for missing axes), n (particles), steps
 *   double  lo_x, hi_x, lo_y, hi_y, lo_z, hi_z, dt, g_x, g_y, g_z, lambda, mu, E
 *   uint8   fixed[ndofs * dim]   1 where dof i, component c is fixed
 *                                (ndofs = (cells_x + 2) (cells_y + 2) (cells_z + 2)
 *                                in 3D, dof index i = ((z index) (cells_y + 2)
 *                                + y index) (cells_x + 2) + x index)
 *   double  x[n dim], v[n dim], u[n dim], m[n], V[n], stress[n dim dim]
 * OUTPUT: x, v, u, V, stress after the steps (same layouts).
 * Each of the REPEAT runs (default 1) starts from the input state; stdout
 * gets "threads T", one line "seconds S" per run (wall time of the step
 * loop only) and "invalid K": the particles found outside the grid, with a
 * non-finite position or velocity, or with det(I + dt L) <= 0 in any step.
 */
#include <math.h>
#include <omp.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define DEGREE 2

/* ------------------------------------------------------------------ axes */

typedef struct {
    int cells;
    double lo, hi, inv_h;
    double *knots; /* the open knot vector: lo x 3, interior breakpoints, hi x 3 */
} Axis;

static void axis_init(Axis *ax, int cells, double lo, double hi)
{
    int j, nk = cells + 1 + 2 * DEGREE;
    ax->cells = cells;
    ax->lo = lo;
    ax->hi = hi;
    ax->inv_h = cells / (hi - lo);
    ax->knots = malloc(nk * sizeof(double));
    for (j = 0; j < DEGREE; j++) {
        ax->knots[j] = lo;
        ax->knots[nk - 1 - j] = hi;
    }
    for (j = 0; j <= cells; j++)
        ax->knots[DEGREE + j] = j == cells ? hi : lo + j * ((hi - lo) / cells); /* as numpy.linspace */
}

/*
 * The cell e of x (clamped to the grid) and the values w[a] and derivatives
 * dw[a] of the three B-splines N_e, N_(e+1), N_(e+2) that are non-zero on it.
 * Interior cells (2 <= e < cells - 2) have the uniform pieces
 *   N = ((1 - xi)^2 / 2, 1/2 + xi (1 - xi), xi^2 / 2),  xi = (x - u_e) / h;
 * the two cells at each end take the Cox-de Boor recursion on the clamped
 * knot vector t (span mu = e + 2; Piegl & Tiller, The NURBS Book, A2.2 and
 * eq. 2.9: N'_(i,2) = 2 N_(i,1) / (t_(i+2) - t_i) - 2 N_(i+1,1) / (t_(i+3) - t_(i+1))).
 */
static int basis(const Axis *ax, double x, double w[3], double dw[3])
{
    double s = (x - ax->lo) * ax->inv_h;
    int e = (int)floor(s);
    if (e < 0)
        e = 0;
    if (e > ax->cells - 1)
        e = ax->cells - 1;
    if (e >= DEGREE && e < ax->cells - DEGREE) {
        double xi = s - e, r = 1.0 - xi, ih = ax->inv_h;
        w[0] = 0.5 * r * r;
        w[1] = 0.5 + xi * r;
        w[2] = 0.5 * xi * xi;
        dw[0] = -r * ih;
        dw[1] = (1.0 - 2.0 * xi) * ih;
        dw[2] = xi * ih;
        return e;
    }
    {
        const double *t = ax->knots;
        int mu = e + DEGREE, a;
        /* degree 1: N_(mu-1,1) and N_(mu,1) */
        double n1[2], left1 = x - t[mu], right1 = t[mu + 1] - x;
        double left2 = x - t[mu - 1], right2 = t[mu + 2] - x;
        n1[0] = right1 / (t[mu + 1] - t[mu]);
        n1[1] = left1 / (t[mu + 1] - t[mu]);
        /* degree 2: N_(mu-2,2), N_(mu-1,2), N_(mu,2) */
        w[0] = right1 / (t[mu + 1] - t[mu - 1]) * n1[0];
        w[1] = left2 / (t[mu + 1] - t[mu - 1]) * n1[0] + right2 / (t[mu + 2] - t[mu]) * n1[1];
        w[2] = left1 / (t[mu + 2] - t[mu]) * n1[1];
        for (a = 0; a < 3; a++) {
            int i = mu - DEGREE + a;
            double d = 0.0;
            if (a >= 1)
                d += 2.0 * n1[a - 1] / (t[i + 2] - t[i]);
            if (a <= 1)
                d -= 2.0 * n1[a] / (t[i + 3] - t[i + 1]);
            dw[a] = d;
        }
    }
    return e;
}

/* ------------------------------------------------------------- the state */

typedef struct {
    int dim, n, steps;
    Axis ax[3];
    int nbx, nby, nbz, ndofs;
    double dt, g[3], lambda, mu, E;
    unsigned char *fixed;
    double *x, *v, *u, *m, *V, *stress;
} Problem;

typedef struct {
    int nthreads, ncomp; /* ncomp = 1 + 2 dim: (m, P, f) per node */
    double **copy;       /* copy[t][k ncomp + c], zero outside [first[t], last[t]) */
    int *first, *last;
    double *a, *vg;      /* grid acceleration and end velocity, (ndofs, dim) */
} Grid;

static void grid_init(Grid *G, const Problem *P)
{
    int t;
    G->nthreads = omp_get_max_threads();
    G->ncomp = 1 + 2 * P->dim;
    G->copy = malloc(G->nthreads * sizeof(double *));
    G->first = malloc(G->nthreads * sizeof(int));
    G->last = malloc(G->nthreads * sizeof(int));
    G->a = malloc((size_t)P->ndofs * P->dim * sizeof(double));
    G->vg = malloc((size_t)P->ndofs * P->dim * sizeof(double));
    for (t = 0; t < G->nthreads; t++)
        G->copy[t] = malloc((size_t)P->ndofs * G->ncomp * sizeof(double));
#pragma omp parallel for schedule(static, 1)
    for (t = 0; t < G->nthreads; t++) { /* first touch by the owning thread */
        memset(G->copy[t], 0, (size_t)P->ndofs * G->ncomp * sizeof(double));
        G->first[t] = 0;
        G->last[t] = 0;
    }
}

/* ------------------------------------------------------- particles to grid */

static void p2g_1d(const Problem *P, Grid *G, int t)
{
    int nt = G->nthreads, lo = (int)((int64_t)t * P->n / nt), hi = (int)((int64_t)(t + 1) * P->n / nt);
    int first = P->ndofs, last = 0, i, a;
    double *g = G->copy[t], w[3], dw[3];
    memset(g + (size_t)G->first[t] * 3, 0, (size_t)(G->last[t] - G->first[t]) * 3 * sizeof(double));
    for (i = lo; i < hi; i++) {
        int e = basis(&P->ax[0], P->x[i], w, dw);
        double mi = P->m[i], pv = mi * P->v[i], s = P->V[i] * P->stress[i];
        for (a = 0; a < 3; a++) {
            double *node = g + (size_t)(e + a) * 3;
            node[0] += w[a] * mi;
            node[1] += w[a] * pv;
            node[2] -= s * dw[a];
        }
        if (e < first)
            first = e;
        if (e + 3 > last)
            last = e + 3;
    }
    G->first[t] = first < last ? first : 0;
    G->last[t] = last;
}

static void p2g_2d(const Problem *P, Grid *G, int t)
{
    int nt = G->nthreads, lo = (int)((int64_t)t * P->n / nt), hi = (int)((int64_t)(t + 1) * P->n / nt);
    int first = P->ndofs, last = 0, i, a, b, nbx = P->nbx;
    double *g = G->copy[t], wx[3], dx[3], wy[3], dy[3];
    memset(g + (size_t)G->first[t] * 5, 0, (size_t)(G->last[t] - G->first[t]) * 5 * sizeof(double));
    for (i = lo; i < hi; i++) {
        int ex = basis(&P->ax[0], P->x[2 * i], wx, dx);
        int ey = basis(&P->ax[1], P->x[2 * i + 1], wy, dy);
        const double *s = P->stress + 4 * i;
        double mi = P->m[i], px = mi * P->v[2 * i], py = mi * P->v[2 * i + 1], Vi = P->V[i];
        double sxx = Vi * s[0], sxy = Vi * 0.5 * (s[1] + s[2]), syy = Vi * s[3];
        int k0 = ey * nbx + ex;
        for (b = 0; b < 3; b++) {
            for (a = 0; a < 3; a++) {
                double N = wx[a] * wy[b], gx = dx[a] * wy[b], gy = wx[a] * dy[b];
                double *node = g + (size_t)(k0 + b * nbx + a) * 5;
                node[0] += N * mi;
                node[1] += N * px;
                node[2] += N * py;
                node[3] -= sxx * gx + sxy * gy;
                node[4] -= sxy * gx + syy * gy;
            }
        }
        if (k0 < first)
            first = k0;
        if (k0 + 2 * nbx + 3 > last)
            last = k0 + 2 * nbx + 3;
    }
    G->first[t] = first < last ? first : 0;
    G->last[t] = last;
}


static void p2g_3d(const Problem *P, Grid *G, int t)
{
    int nt = G->nthreads, lo = (int)((int64_t)t * P->n / nt), hi = (int)((int64_t)(t + 1) * P->n / nt);
    int first = P->ndofs, last = 0, i, a, b, c, nbx = P->nbx, nbxy = P->nbx * P->nby;
    double *g = G->copy[t], wx[3], dx[3], wy[3], dy[3], wz[3], dz[3];
    memset(g + (size_t)G->first[t] * 7, 0, (size_t)(G->last[t] - G->first[t]) * 7 * sizeof(double));
    for (i = lo; i < hi; i++) {
        int ex = basis(&P->ax[0], P->x[3 * i], wx, dx);
        int ey = basis(&P->ax[1], P->x[3 * i + 1], wy, dy);
        int ez = basis(&P->ax[2], P->x[3 * i + 2], wz, dz);
        const double *s = P->stress + 9 * i;
        double mi = P->m[i], px = mi * P->v[3 * i], py = mi * P->v[3 * i + 1];
        double pz = mi * P->v[3 * i + 2], Vi = P->V[i];
        double sxx = Vi * s[0], syy = Vi * s[4], szz = Vi * s[8];
        double sxy = Vi * 0.5 * (s[1] + s[3]), sxz = Vi * 0.5 * (s[2] + s[6]);
        double syz = Vi * 0.5 * (s[5] + s[7]);
        int k0 = ez * nbxy + ey * nbx + ex;
        for (c = 0; c < 3; c++) {
            for (b = 0; b < 3; b++) {
                double wyz = wy[b] * wz[c], dyz = dy[b] * wz[c], ydz = wy[b] * dz[c];
                double *row = g + (size_t)(k0 + c * nbxy + b * nbx) * 7;
                for (a = 0; a < 3; a++) {
                    double N = wx[a] * wyz, gx = dx[a] * wyz, gy = wx[a] * dyz, gz = wx[a] * ydz;
                    double *node = row + 7 * a;
                    node[0] += N * mi;
                    node[1] += N * px;
                    node[2] += N * py;
                    node[3] += N * pz;
                    node[4] -= sxx * gx + sxy * gy + sxz * gz;
                    node[5] -= sxy * gx + syy * gy + syz * gz;
                    node[6] -= sxz * gx + syz * gy + szz * gz;
                }
            }
        }
        if (k0 < first)
            first = k0;
        if (k0 + 2 * nbxy + 2 * nbx + 3 > last)
            last = k0 + 2 * nbxy + 2 * nbx + 3;
    }
    G->first[t] = first < last ? first : 0;
    G->last[t] = last;
}

/* ------------------------------------------------------------- grid update */

/* Sum the thread copies of node k, then a = f / m + g and v = P / m + dt a on
   free dofs with mass (0 on fixed and empty dofs). */
static void grid_update(const Problem *P, Grid *G)
{
    int k, dim = P->dim, nc = G->ncomp, nt = G->nthreads;
#pragma omp parallel for schedule(static)
    for (k = 0; k < P->ndofs; k++) {
        double sum[7] = {0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0};
        int t, c;
        for (t = 0; t < nt; t++) {
            if (k >= G->first[t] && k < G->last[t]) {
                const double *node = G->copy[t] + (size_t)k * nc;
                for (c = 0; c < nc; c++)
                    sum[c] += node[c];
            }
        }
        for (c = 0; c < dim; c++) {
            double a = 0.0, v = 0.0;
            if (!P->fixed[k * dim + c] && sum[0] > 0.0) {
                a = sum[1 + dim + c] / sum[0] + P->g[c];
                v = sum[1 + c] / sum[0] + P->dt * a;
            }
            G->a[k * dim + c] = a;
            G->vg[k * dim + c] = v;
        }
    }
}

/* --------------------------------------------------------- grid to particles */

static int outside(const Axis *ax, double x)
{
    return !(x >= ax->lo && x <= ax->hi);
}

static long g2p_1d(Problem *P, const Grid *G)
{
    long invalid = 0;
    int i;
    double dt = P->dt, E = P->E;
#pragma omp parallel for schedule(static) reduction(+ : invalid)
    for (i = 0; i < P->n; i++) {
        double w[3], dw[3], acc = 0.0, vel = 0.0, L = 0.0, J;
        int e = basis(&P->ax[0], P->x[i], w, dw), a;
        for (a = 0; a < 3; a++) {
            acc += w[a] * G->a[e + a];
            vel += w[a] * G->vg[e + a];
            L += dw[a] * G->vg[e + a];
        }
        P->v[i] += dt * acc;
        P->x[i] += dt * vel;
        P->u[i] += dt * vel;
        P->stress[i] += dt * E * L;
        J = 1.0 + dt * L;
        P->V[i] *= J;
        if (!(J > 0.0) || !isfinite(P->x[i]) || !isfinite(P->v[i]) || outside(&P->ax[0], P->x[i]))
            invalid++;
    }
    return invalid;
}

static long g2p_2d(Problem *P, const Grid *G)
{
    long invalid = 0;
    int i, nbx = P->nbx;
    double dt = P->dt, lambda = P->lambda, mu = P->mu;
#pragma omp parallel for schedule(static) reduction(+ : invalid)
    for (i = 0; i < P->n; i++) {
        double wx[3], dx[3], wy[3], dy[3];
        double ax = 0.0, ay = 0.0, vx = 0.0, vy = 0.0, Lxx = 0.0, Lxy = 0.0, Lyx = 0.0, Lyy = 0.0;
        double Dxx, Dyy, Dxy, tr, J, *s = P->stress + 4 * i, *x = P->x + 2 * i, *v = P->v + 2 * i;
        int ex = basis(&P->ax[0], x[0], wx, dx), ey = basis(&P->ax[1], x[1], wy, dy), a, b;
        for (b = 0; b < 3; b++) {
            for (a = 0; a < 3; a++) {
                int k = (ey + b) * nbx + ex + a;
                double N = wx[a] * wy[b], gx = dx[a] * wy[b], gy = wx[a] * dy[b];
                double gvx = G->vg[2 * k], gvy = G->vg[2 * k + 1];
                ax += N * G->a[2 * k];
                ay += N * G->a[2 * k + 1];
                vx += N * gvx;
                vy += N * gvy;
                Lxx += gvx * gx;
                Lxy += gvx * gy;
                Lyx += gvy * gx;
                Lyy += gvy * gy;
            }
        }
        v[0] += dt * ax;
        v[1] += dt * ay;
        x[0] += dt * vx;
        x[1] += dt * vy;
        P->u[2 * i] += dt * vx;
        P->u[2 * i + 1] += dt * vy;
        Dxx = dt * Lxx;
        Dyy = dt * Lyy;
        Dxy = 0.5 * dt * (Lxy + Lyx);
        tr = lambda * (Dxx + Dyy);
        s[0] += tr + 2.0 * mu * Dxx;
        s[1] += 2.0 * mu * Dxy;
        s[2] += 2.0 * mu * Dxy;
        s[3] += tr + 2.0 * mu * Dyy;
        J = (1.0 + dt * Lxx) * (1.0 + dt * Lyy) - dt * dt * Lxy * Lyx;
        P->V[i] *= J;
        if (!(J > 0.0) || !isfinite(x[0]) || !isfinite(x[1]) || !isfinite(v[0]) || !isfinite(v[1])
            || outside(&P->ax[0], x[0]) || outside(&P->ax[1], x[1]))
            invalid++;
    }
    return invalid;
}


static long g2p_3d(Problem *P, const Grid *G)
{
    long invalid = 0;
    int i, nbx = P->nbx, nbxy = P->nbx * P->nby;
    double dt = P->dt, lambda = P->lambda, mu = P->mu;
#pragma omp parallel for schedule(static) reduction(+ : invalid)
    for (i = 0; i < P->n; i++) {
        double wx[3], dx[3], wy[3], dy[3], wz[3], dz[3], A[3] = {0.0, 0.0, 0.0};
        double U[3] = {0.0, 0.0, 0.0}, L[3][3] = {{0.0}}, D[3][3], F[3][3], tr, J;
        double *s = P->stress + 9 * i, *x = P->x + 3 * i, *v = P->v + 3 * i, *u = P->u + 3 * i;
        int ex = basis(&P->ax[0], x[0], wx, dx), ey = basis(&P->ax[1], x[1], wy, dy);
        int ez = basis(&P->ax[2], x[2], wz, dz), a, b, c, d;
        for (c = 0; c < 3; c++) {
            for (b = 0; b < 3; b++) {
                double wyz = wy[b] * wz[c], dyz = dy[b] * wz[c], ydz = wy[b] * dz[c];
                int row = (ez + c) * nbxy + (ey + b) * nbx + ex;
                for (a = 0; a < 3; a++) {
                    const double *ga = G->a + 3 * (row + a), *gv = G->vg + 3 * (row + a);
                    double N = wx[a] * wyz, grad[3];
                    grad[0] = dx[a] * wyz;
                    grad[1] = wx[a] * dyz;
                    grad[2] = wx[a] * ydz;
                    for (d = 0; d < 3; d++) {
                        int e;
                        A[d] += N * ga[d];
                        U[d] += N * gv[d];
                        for (e = 0; e < 3; e++)
                            L[d][e] += gv[d] * grad[e];
                    }
                }
            }
        }
        for (d = 0; d < 3; d++) {
            v[d] += dt * A[d];
            x[d] += dt * U[d];
            u[d] += dt * U[d];
        }
        for (d = 0; d < 3; d++) {
            int e;
            for (e = 0; e < 3; e++) {
                D[d][e] = 0.5 * dt * (L[d][e] + L[e][d]);
                F[d][e] = (d == e ? 1.0 : 0.0) + dt * L[d][e];
            }
        }
        tr = lambda * (D[0][0] + D[1][1] + D[2][2]);
        for (d = 0; d < 3; d++) {
            int e;
            for (e = 0; e < 3; e++)
                s[3 * d + e] += (d == e ? tr : 0.0) + 2.0 * mu * D[d][e];
        }
        J = F[0][0] * (F[1][1] * F[2][2] - F[1][2] * F[2][1])
            - F[0][1] * (F[1][0] * F[2][2] - F[1][2] * F[2][0])
            + F[0][2] * (F[1][0] * F[2][1] - F[1][1] * F[2][0]);
        P->V[i] *= J;
        if (!(J > 0.0) || !isfinite(x[0]) || !isfinite(x[1]) || !isfinite(x[2])
            || !isfinite(v[0]) || !isfinite(v[1]) || !isfinite(v[2])
            || outside(&P->ax[0], x[0]) || outside(&P->ax[1], x[1]) || outside(&P->ax[2], x[2]))
            invalid++;
    }
    return invalid;
}

/* ---------------------------------------------------------------- the loop */

static long run_steps(Problem *P, Grid *G)
{
    long invalid = 0;
    int step;
    for (step = 0; step < P->steps; step++) {
#pragma omp parallel num_threads(G->nthreads)
        {
            int t = omp_get_thread_num();
            if (P->dim == 1)
                p2g_1d(P, G, t);
            else if (P->dim == 2)
                p2g_2d(P, G, t);
            else
                p2g_3d(P, G, t);
        }
        grid_update(P, G);
        invalid += P->dim == 1 ? g2p_1d(P, G) : P->dim == 2 ? g2p_2d(P, G) : g2p_3d(P, G);
    }
    return invalid;
}

/* -------------------------------------------------------------------- I/O */

static void fail(const char *what, const char *detail)
{
    fprintf(stderr, "usl_step: %s%s%s\n", what, detail ? ": " : "", detail ? detail : "");
    exit(2);
}

static void read_exactly(FILE *f, void *to, size_t size, size_t count, const char *what)
{
    if (fread(to, size, count, f) != count)
        fail("input ended early while reading", what);
}

static double *read_doubles(FILE *f, size_t count, const char *what)
{
    double *a = malloc((count ? count : 1) * sizeof(double));
    if (!a)
        fail("out of memory for", what);
    read_exactly(f, a, sizeof(double), count, what);
    return a;
}

static void read_problem(const char *path, Problem *P)
{
    char magic[8];
    int64_t head[6];
    double par[13];
    size_t n, dim;
    FILE *f = fopen(path, "rb");
    if (!f)
        fail("cannot open the input", path);
    read_exactly(f, magic, 1, 8, "magic");
    if (memcmp(magic, "USLSTEP2", 8) != 0)
        fail("not a usl_step input (magic USLSTEP2)", path);
    read_exactly(f, head, sizeof(int64_t), 6, "header");
    read_exactly(f, par, sizeof(double), 13, "parameters");
    if (head[0] < 1 || head[0] > 3 || head[1] < 2 * DEGREE || head[2] < 1 || head[3] < 1
        || head[4] < 1 || head[5] < 0 || (head[0] >= 2 && head[2] < 2 * DEGREE)
        || (head[0] == 3 && head[3] < 2 * DEGREE))
        fail("invalid header (dim 1 to 3, at least 4 cells per axis, n >= 1, steps >= 0)", path);
    P->dim = (int)head[0];
    P->n = (int)head[4];
    P->steps = (int)head[5];
    axis_init(&P->ax[0], (int)head[1], par[0], par[1]);
    axis_init(&P->ax[1], (int)head[2], par[2], par[3]);
    axis_init(&P->ax[2], (int)head[3], par[4], par[5]);
    P->nbx = (int)head[1] + DEGREE;
    P->nby = P->dim >= 2 ? (int)head[2] + DEGREE : 1;
    P->nbz = P->dim == 3 ? (int)head[3] + DEGREE : 1;
    P->ndofs = P->nbx * P->nby * P->nbz;
    P->dt = par[6];
    P->g[0] = par[7];
    P->g[1] = par[8];
    P->g[2] = par[9];
    P->lambda = par[10];
    P->mu = par[11];
    P->E = par[12];
    n = (size_t)P->n;
    dim = (size_t)P->dim;
    P->fixed = malloc((size_t)P->ndofs * dim);
    read_exactly(f, P->fixed, 1, (size_t)P->ndofs * dim, "fixed");
    P->x = read_doubles(f, n * dim, "x");
    P->v = read_doubles(f, n * dim, "v");
    P->u = read_doubles(f, n * dim, "u");
    P->m = read_doubles(f, n, "m");
    P->V = read_doubles(f, n, "V");
    P->stress = read_doubles(f, n * dim * dim, "stress");
    fclose(f);
}

static void write_doubles(FILE *f, const double *a, size_t count)
{
    if (fwrite(a, sizeof(double), count, f) != count)
        fail("cannot write the output", NULL);
}

int main(int argc, char **argv)
{
    Problem P, start;
    Grid G;
    FILE *out;
    int repeat = 1, r;
    long invalid = 0;
    size_t n, dim;
    if (argc < 3 || argc > 4)
        fail("usage: usl_step INPUT OUTPUT [REPEAT]", NULL);
    if (argc == 4 && (repeat = atoi(argv[3])) < 1)
        fail("REPEAT must be a positive integer", argv[3]);
    read_problem(argv[1], &start);
    n = (size_t)start.n;
    dim = (size_t)start.dim;
    P = start; /* the runs work on copies of the particle arrays */
    P.x = malloc(n * dim * sizeof(double));
    P.v = malloc(n * dim * sizeof(double));
    P.u = malloc(n * dim * sizeof(double));
    P.V = malloc(n * sizeof(double));
    P.stress = malloc(n * dim * dim * sizeof(double));
    grid_init(&G, &P);
    printf("threads %d\n", G.nthreads);
    for (r = 0; r < repeat; r++) {
        double t0;
        memcpy(P.x, start.x, n * dim * sizeof(double));
        memcpy(P.v, start.v, n * dim * sizeof(double));
        memcpy(P.u, start.u, n * dim * sizeof(double));
        memcpy(P.V, start.V, n * sizeof(double));
        memcpy(P.stress, start.stress, n * dim * dim * sizeof(double));
        t0 = omp_get_wtime();
        invalid = run_steps(&P, &G);
        printf("seconds %.9f\n", omp_get_wtime() - t0);
    }
    printf("invalid %ld\n", invalid);
    out = fopen(argv[2], "wb");
    if (!out)
        fail("cannot open the output", argv[2]);
    write_doubles(out, P.x, n * dim);
    write_doubles(out, P.v, n * dim);
    write_doubles(out, P.u, n * dim);
    write_doubles(out, P.V, n);
    write_doubles(out, P.stress, n * dim * dim);
    fclose(out);
    return 0;
}
