/*
 * hil.geometry._native: the per-pair marker geometry of the controller in compiled code.
 *
 *   horn:  Horn's closed-form registration, unit or given weights (hil.geometry.registration.
 *          register_horn, seed 000 eqs 17-21), with that module's configuration checks;
 *   track: the greedy frame-to-frame marker assignment (hil.controller.registration.track);
 *   ur_newton: the Newton steps of a UR arm's inverse kinematics for a small step
 *          (hil.kinematics.ur.ur_newton_ik: the simulated arm's servo command, every period);
 *   filter_feed, filter_pose, tcp_setpoint: the per-pair control law of COMPENSATE, the motion
 *          filter's step and pose (hil.controller.compensation.MotionFilter) and the tracking
 *          setpoint with its velocity (hil.controller.estimate.Estimate.tracking_setpoint);
 *   ar_feed, ar_forecast: the loop's "ar-ls" predictor (hil.prediction.ar.ArModel): its update
 *          and forecast, once and twice per pair in COMPENSATE;
 *   local_change: the 'weighted' and 'local-tps' change estimators' per-pair fit (hil.controller.
 *          change_estimate), once per pair when the estimator is not 'rigid';
 *   target_score, target_turn, turn_about: the surrogate target model's per-pair steering
 *          (hil.controller.target_model: the breathing score, the path's turn at the modelled
 *          target, the faded turn about the entry), once per pair when target_model = "surrogate".
 *
 * Why: horn, track and the control law run for every stereo pair on the path from the exposure
 * to the servo setpoint, ur_newton in every servo period between the setpoint and the command. On a
 * shared host, numpy code that runs once per camera period finds its instructions and data
 * evicted and takes several times its hot-loop time (docs/benchmarks.md); this code is small.
 *
 * Contract: only the Python C API and the buffer protocol. Every array is float64, C-contiguous,
 * with the documented shape; outputs are written into arrays the caller allocated; a bad buffer
 * raises TypeError / ValueError naming the argument. No global mutable state; the GIL is held
 * throughout (a call is a few microseconds).
 *
 * horn does not raise for bad points: it returns -1.0 for every input the numpy code refuses or
 * might refuse (fewer than 3 pairs, NaN/inf, a coincident or collinear set, an eigen-solution
 * that did not converge, a result that overflowed); the caller then runs the numpy code, which
 * raises the typed error with its message. Results agree with the numpy code to rounding: the eigenvectors come from cyclic
 * Jacobi rotations instead of LAPACK, and sums run in index order.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <string.h>

/* hil.geometry.registration's thresholds (COINCIDENT_TOL_MM, COLLINEAR_REL_TOL) */
#define COINCIDENT_TOL_MM 1e-9
#define COLLINEAR_REL_TOL 1e-6
#define MAX_COORDINATE_MM 1e9   /* hil.geometry.registration.MAX_COORDINATE_MM */
#define JACOBI_MAX_SWEEPS 60

/* ---- buffers ------------------------------------------------------------------------------ */

/* A float64 C-contiguous buffer of ``ndim`` dimensions; shape[i] < 0: any length. The view is
 * released by the caller (view->obj != NULL once acquired). */
static double *get_f64(PyObject *obj, Py_buffer *view, const char *name, int ndim,
                       const Py_ssize_t *shape, int writable)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    view->obj = NULL;
    if (PyObject_GetBuffer(obj, view, flags) != 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s: expected a %s C-contiguous float64 array, got %.100s", name,
                     writable ? "writable" : "readable", Py_TYPE(obj)->tp_name);
        return NULL;
    }
    const char *fmt = view->format ? view->format : "B";
    if (fmt[0] == '@' || fmt[0] == '=' || fmt[0] == '<') {
        fmt++;
    }
    if (strcmp(fmt, "d") != 0 || view->itemsize != 8) {
        PyErr_Format(PyExc_TypeError, "%s: expected float64 items, got format '%s'", name, fmt);
        return NULL;
    }
    if (view->ndim != ndim) {
        PyErr_Format(PyExc_ValueError, "%s: expected %d dimension(s), got %d", name, ndim, view->ndim);
        return NULL;
    }
    for (int i = 0; i < ndim; i++) {
        if (shape[i] >= 0 && view->shape[i] != shape[i]) {
            PyErr_Format(PyExc_ValueError, "%s: dimension %d has length %zd, expected %zd", name, i,
                         view->shape[i], shape[i]);
            return NULL;
        }
    }
    return (double *)view->buf;
}

static void release(Py_buffer *views, int n)
{
    for (int i = 0; i < n; i++) {
        if (views[i].obj != NULL) {
            PyBuffer_Release(&views[i]);
        }
    }
}

/* One buffer of a call: its name, dimensions (1: (len[0],), 2: (len[0], len[1])), whether it is
 * written. */
typedef struct {
    const char *name;
    int ndim;
    Py_ssize_t len[2];
    int writable;
} BufSpec;

/* get_f64 for objs[i] by spec[i], i < n, into p[i]; 0, or -1 with the error set at the first bad
 * one. The caller releases all n views (zeroed here first) either way. */
static int get_all(PyObject *const *objs, const BufSpec *spec, int n, Py_buffer *views, double **p)
{
    memset(views, 0, (size_t)n * sizeof(Py_buffer));
    for (int i = 0; i < n; i++) {
        p[i] = get_f64(objs[i], &views[i], spec[i].name, spec[i].ndim, spec[i].len, spec[i].writable);
        if (p[i] == NULL) {
            return -1;
        }
    }
    return 0;
}

/* ---- symmetric eigen-decomposition (n <= 4) ------------------------------------------------ */

/* Cyclic Jacobi rotations on the symmetric n x n matrix ``a`` (row-major 4 x 4 storage, destroyed:
 * its diagonal becomes the eigenvalues); ``v`` (may be NULL) receives the eigenvectors as columns.
 * Each rotation zeroes a[p][q] (t = sgn(theta) / (|theta| + sqrt(theta^2 + 1)), theta =
 * (a_qq - a_pp) / (2 a_pq)). Returns 0 once the off-diagonal part is below rounding of the
 * matrix's norm, -1 when it did not get there in JACOBI_MAX_SWEEPS sweeps. */
static int jacobi_sym(int n, double a[4][4], double v[4][4])
{
    if (v != NULL) {
        for (int i = 0; i < n; i++) {
            for (int j = 0; j < n; j++) {
                v[i][j] = i == j ? 1.0 : 0.0;
            }
        }
    }
    double norm2 = 0.0;
    for (int i = 0; i < n; i++) {
        for (int j = 0; j < n; j++) {
            norm2 += a[i][j] * a[i][j];
        }
    }
    for (int sweep = 0; sweep < JACOBI_MAX_SWEEPS; sweep++) {
        double off2 = 0.0;
        for (int p = 0; p < n; p++) {
            for (int q = p + 1; q < n; q++) {
                off2 += a[p][q] * a[p][q];
            }
        }
        if (off2 <= 1e-34 * norm2) {   /* (1e-17)^2: below the rounding of the largest entries */
            return 0;
        }
        for (int p = 0; p < n; p++) {
            for (int q = p + 1; q < n; q++) {
                double apq = a[p][q];
                if (apq == 0.0) {
                    continue;
                }
                double theta = (a[q][q] - a[p][p]) / (2.0 * apq);
                double t;
                if (fabs(theta) > 1e150) {
                    t = 0.5 / theta;   /* theta^2 would overflow; t ~ 1 / (2 theta) */
                } else {
                    t = (theta >= 0.0 ? 1.0 : -1.0) / (fabs(theta) + sqrt(theta * theta + 1.0));
                }
                double c = 1.0 / sqrt(t * t + 1.0);
                double s = t * c;
                for (int k = 0; k < n; k++) {   /* columns p, q of A P */
                    double akp = a[k][p], akq = a[k][q];
                    a[k][p] = c * akp - s * akq;
                    a[k][q] = s * akp + c * akq;
                }
                for (int k = 0; k < n; k++) {   /* rows p, q of P^T (A P) */
                    double apk = a[p][k], aqk = a[q][k];
                    a[p][k] = c * apk - s * aqk;
                    a[q][k] = s * apk + c * aqk;
                }
                a[p][q] = 0.0;
                a[q][p] = 0.0;
                if (v != NULL) {
                    for (int k = 0; k < n; k++) {
                        double vkp = v[k][p], vkq = v[k][q];
                        v[k][p] = c * vkp - s * vkq;
                        v[k][q] = s * vkp + c * vkq;
                    }
                }
            }
        }
    }
    return -1;
}

/* ---- horn ----------------------------------------------------------------------------------- */

/* 0 when ``pts`` (n x 3) fixes a rotation by registration.py's rule (its centred set's singular
 * values: the largest above COINCIDENT_TOL_MM * max(1, max |p|), the second above
 * COLLINEAR_REL_TOL times the largest), else -1. The singular values are the square roots of the
 * eigenvalues of the centred scatter matrix. ``w`` (n, or NULL: all): only the points with a
 * positive weight count, as the numpy code checks the active pairs. */
static int configuration_ok(const double *pts, Py_ssize_t n, const double *w)
{
    double mean[3] = {0.0, 0.0, 0.0};
    double scale = 0.0;
    Py_ssize_t used = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (w != NULL && !(w[i] > 0.0)) {
            continue;
        }
        used++;
        for (int j = 0; j < 3; j++) {
            double x = pts[3 * i + j];
            mean[j] += x;
            if (fabs(x) > scale) {
                scale = fabs(x);
            }
        }
    }
    if (used < 3) {
        return -1;
    }
    for (int j = 0; j < 3; j++) {
        mean[j] /= (double)used;
    }
    double s[4][4] = {{0.0}};
    for (Py_ssize_t i = 0; i < n; i++) {
        if (w != NULL && !(w[i] > 0.0)) {
            continue;
        }
        double d[3];
        for (int j = 0; j < 3; j++) {
            d[j] = pts[3 * i + j] - mean[j];
        }
        for (int j = 0; j < 3; j++) {
            for (int k = 0; k < 3; k++) {
                s[j][k] += d[j] * d[k];
            }
        }
    }
    if (jacobi_sym(3, s, NULL) != 0) {
        return -1;
    }
    double ev[3] = {s[0][0], s[1][1], s[2][2]};
    for (int i = 0; i < 3; i++) {   /* descending */
        for (int j = i + 1; j < 3; j++) {
            if (ev[j] > ev[i]) {
                double tmp = ev[i];
                ev[i] = ev[j];
                ev[j] = tmp;
            }
        }
    }
    double sv0 = sqrt(ev[0] > 0.0 ? ev[0] : 0.0);
    double sv1 = sqrt(ev[1] > 0.0 ? ev[1] : 0.0);
    if (sv0 <= COINCIDENT_TOL_MM * (scale > 1.0 ? scale : 1.0)) {
        return -1;
    }
    if (sv1 <= COLLINEAR_REL_TOL * sv0) {
        return -1;
    }
    return 0;
}

static int all_finite(const double *x, Py_ssize_t count)
{
    for (Py_ssize_t i = 0; i < count; i++) {
        if (!isfinite(x[i])) {
            return 0;
        }
    }
    return 1;
}

/* Whether every value is finite and within +-bound (NaN fails the comparison). */
static int all_within(const double *x, Py_ssize_t count, double bound)
{
    for (Py_ssize_t i = 0; i < count; i++) {
        if (!(fabs(x[i]) <= bound)) {
            return 0;
        }
    }
    return 1;
}

PyDoc_STRVAR(horn_doc,
"horn(fixed, moving, R, t, residuals, weights=None) -> float\n\n"
"Horn's registration (hil.geometry.registration.register_horn): fixed, moving (N, 3) float64\n"
"C-contiguous, mm; weights (N,) float64 or None (unit weights); writes R (3, 3) and t (3,) of\n"
"T_fixed_from_moving and the residuals (N,) |R m_i + t - f_i| in mm; returns the FRE (the\n"
"weighted RMS of the residuals, mm). Returns -1.0 (outputs undefined) for N < 3, NaN/inf or a\n"
"coordinate beyond 1e9 mm, a weight that is negative or not finite, fewer than 3 positive\n"
"weights, a coincident or collinear set of the weighted pairs, no convergence or a non-finite\n"
"result: the numpy code decides those (and raises). TypeError / ValueError for a bad buffer.");

/* Whether the weights are finite, non-negative, at least 3 positive and their sum finite. */
static int weights_ok(const double *w, Py_ssize_t n)
{
    Py_ssize_t positive = 0;
    double sum = 0.0;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (!isfinite(w[i]) || w[i] < 0.0) {
            return 0;
        }
        positive += w[i] > 0.0;
        sum += w[i];
    }
    return positive >= 3 && isfinite(sum);
}

/* Horn's registration of moving (n x 3) onto fixed (n x 3), weights w (n, or NULL: unit): writes
 * R (row-major 3 x 3), t (3) and the residuals res (n); returns the FRE (mm), or -1.0 for every
 * input registration.py refuses or might refuse (k_horn's doc). */
static double horn_solve(const double *f, const double *m, const double *w, Py_ssize_t n, double *R,
                         double *t, double *res)
{
    if (n < 3 || !all_within(f, 3 * n, MAX_COORDINATE_MM) || !all_within(m, 3 * n, MAX_COORDINATE_MM)
        || (w != NULL && !weights_ok(w, n))
        || configuration_ok(f, n, w) != 0 || configuration_ok(m, n, w) != 0) {
        return -1.0;
    }
    /* eq 17 with wn_i = w_i / sum w (1/N without weights): centroids and
     * A = sum wn_i (m_i - m_bar)(f_i - f_bar)^T, in the numpy code's order of operations */
    double w_sum = 0.0;
    for (Py_ssize_t i = 0; w != NULL && i < n; i++) {
        w_sum += w[i];
    }
#define WN(i) (w == NULL ? 1.0 / (double)n : w[(i)] / w_sum)
    double f_bar[3] = {0.0, 0.0, 0.0}, m_bar[3] = {0.0, 0.0, 0.0};
    for (Py_ssize_t i = 0; i < n; i++) {
        double wn = WN(i);
        for (int j = 0; j < 3; j++) {
            f_bar[j] += wn * f[3 * i + j];
            m_bar[j] += wn * m[3 * i + j];
        }
    }
    double A[3][3] = {{0.0}};
    for (Py_ssize_t i = 0; i < n; i++) {
        double wn = WN(i);
        for (int j = 0; j < 3; j++) {
            double mj = (m[3 * i + j] - m_bar[j]) * wn;
            for (int k = 0; k < 3; k++) {
                A[j][k] += mj * (f[3 * i + k] - f_bar[k]);
            }
        }
    }
    /* eqs 18-20: Delta = [B23, B31, B12] of B = A - A^T; C = [[tr A, Delta^T], [Delta, A + A^T - tr(A) I]] */
    double tr = A[0][0] + A[1][1] + A[2][2];
    double delta[3] = {A[1][2] - A[2][1], A[2][0] - A[0][2], A[0][1] - A[1][0]};
    double C[4][4], V[4][4];
    C[0][0] = tr;
    for (int j = 0; j < 3; j++) {
        C[0][j + 1] = delta[j];
        C[j + 1][0] = delta[j];
        for (int k = 0; k < 3; k++) {
            C[j + 1][k + 1] = A[j][k] + A[k][j] - (j == k ? tr : 0.0);
        }
    }
    if (jacobi_sym(4, C, V) != 0) {
        return -1.0;
    }
    int best = 0;   /* eq 21: the eigenvector of the largest eigenvalue */
    for (int i = 1; i < 4; i++) {
        if (C[i][i] > C[best][best]) {
            best = i;
        }
    }
    double q[4] = {V[0][best], V[1][best], V[2][best], V[3][best]};
    double qn = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if (!(qn >= 1e-12)) {
        return -1.0;
    }
    double q0 = q[0] / qn, q1 = q[1] / qn, q2 = q[2] / qn, q3 = q[3] / qn;
    /* eq 16 (hil.geometry.transform.quaternion_to_matrix) */
    R[0] = q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3;
    R[1] = 2 * (q1 * q2 - q0 * q3);
    R[2] = 2 * (q1 * q3 + q0 * q2);
    R[3] = 2 * (q1 * q2 + q0 * q3);
    R[4] = q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3;
    R[5] = 2 * (q2 * q3 - q0 * q1);
    R[6] = 2 * (q1 * q3 - q0 * q2);
    R[7] = 2 * (q2 * q3 + q0 * q1);
    R[8] = q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3;
    for (int j = 0; j < 3; j++) {   /* t = f_bar - R m_bar */
        t[j] = f_bar[j] - (R[3 * j] * m_bar[0] + R[3 * j + 1] * m_bar[1] + R[3 * j + 2] * m_bar[2]);
    }
    double sum_r2 = 0.0;
    for (Py_ssize_t i = 0; i < n; i++) {
        double r2 = 0.0;
        for (int j = 0; j < 3; j++) {
            double d = R[3 * j] * m[3 * i] + R[3 * j + 1] * m[3 * i + 1] + R[3 * j + 2] * m[3 * i + 2]
                       + t[j] - f[3 * i + j];
            r2 += d * d;
        }
        res[i] = sqrt(r2);
        sum_r2 += w == NULL ? r2 : w[i] * res[i] * res[i];   /* numpy: w @ residuals**2 */
    }
#undef WN
    double fre = sqrt(sum_r2 / (w == NULL ? (double)n : w_sum));
    /* coordinates so large that a square overflows: never a non-finite transform (numpy decides) */
    return all_finite(R, 9) && all_finite(t, 3) && all_finite(res, n) && isfinite(fre) ? fre : -1.0;
}

static PyObject *k_horn(PyObject *self, PyObject *args)
{
    PyObject *o_f, *o_m, *o_R, *o_t, *o_res, *o_w = Py_None;
    if (!PyArg_ParseTuple(args, "OOOOO|O", &o_f, &o_m, &o_R, &o_t, &o_res, &o_w)) {
        return NULL;
    }
    Py_buffer views[6];
    memset(views, 0, sizeof(views));
    PyObject *result = NULL;
    const Py_ssize_t any3[2] = {-1, 3};
    const Py_ssize_t s33[2] = {3, 3};
    const Py_ssize_t s3[1] = {3};
    const double *f = get_f64(o_f, &views[0], "fixed", 2, any3, 0);
    if (f == NULL) {
        goto done;
    }
    Py_ssize_t n = views[0].shape[0];
    const Py_ssize_t n3[2] = {n, 3};
    const Py_ssize_t sn[1] = {n};
    const double *m = get_f64(o_m, &views[1], "moving", 2, n3, 0);
    double *R = m == NULL ? NULL : get_f64(o_R, &views[2], "R", 2, s33, 1);
    double *t = R == NULL ? NULL : get_f64(o_t, &views[3], "t", 1, s3, 1);
    double *res = t == NULL ? NULL : get_f64(o_res, &views[4], "residuals", 1, sn, 1);
    if (res == NULL) {
        goto done;
    }
    const double *w = NULL;
    if (o_w != Py_None && (w = get_f64(o_w, &views[5], "weights", 1, sn, 0)) == NULL) {
        goto done;
    }
    result = PyFloat_FromDouble(horn_solve(f, m, w, n, R, t, res));
done:
    release(views, 6);
    return result;
}

/* ---- track ---------------------------------------------------------------------------------- */

#define TRACK_MAX 4096   /* predicted rows x points: more goes the numpy way */

PyDoc_STRVAR(track_doc,
"track(points, predicted, tolerance_mm, out) -> bool\n\n"
"The greedy unique nearest assignment of hil.controller.registration.track: points (M, 3),\n"
"predicted (K, 3) (NaN rows skipped), out (K, 3) float64 C-contiguous, mm. Repeatedly the\n"
"closest free (predicted row, point) pair within tolerance_mm is assigned (ties: the lower\n"
"row-major index, as a stable sort would); out gets the assigned points, NaN elsewhere. A\n"
"distance that is NaN never matches. Returns False (out untouched) when K, M or K * M is over\n"
"4096 (the numpy code then runs). TypeError / ValueError for a bad buffer.");

static PyObject *k_track(PyObject *self, PyObject *args)
{
    PyObject *o_p, *o_pred, *o_out;
    double tol;
    if (!PyArg_ParseTuple(args, "OOdO", &o_p, &o_pred, &tol, &o_out)) {
        return NULL;
    }
    Py_buffer views[3];
    memset(views, 0, sizeof(views));
    PyObject *result = NULL;
    const Py_ssize_t any3[2] = {-1, 3};
    const double *pts = get_f64(o_p, &views[0], "points", 2, any3, 0);
    const double *pred = pts == NULL ? NULL : get_f64(o_pred, &views[1], "predicted", 2, any3, 0);
    if (pred == NULL) {
        goto done;
    }
    Py_ssize_t m = views[0].shape[0], k = views[1].shape[0];
    const Py_ssize_t k3[2] = {k, 3};
    double *out = get_f64(o_out, &views[2], "out", 2, k3, 1);
    if (out == NULL) {
        goto done;
    }
    if (k > TRACK_MAX || m > TRACK_MAX || k * m > TRACK_MAX) {   /* each bounds an array below */
        result = Py_NewRef(Py_False);
        goto done;
    }
    double d[TRACK_MAX];
    unsigned char row_used[TRACK_MAX], col_used[TRACK_MAX];
    for (Py_ssize_t r = 0; r < k; r++) {
        int valid = isfinite(pred[3 * r]) && isfinite(pred[3 * r + 1]) && isfinite(pred[3 * r + 2]);
        for (Py_ssize_t c = 0; c < m; c++) {
            if (!valid) {
                d[r * m + c] = INFINITY;
                continue;
            }
            double dx = pred[3 * r] - pts[3 * c], dy = pred[3 * r + 1] - pts[3 * c + 1];
            double dz = pred[3 * r + 2] - pts[3 * c + 2];
            d[r * m + c] = sqrt(dx * dx + dy * dy + dz * dz);
        }
        row_used[r] = 0;
        out[3 * r] = out[3 * r + 1] = out[3 * r + 2] = NAN;
    }
    for (Py_ssize_t c = 0; c < m; c++) {
        col_used[c] = 0;
    }
    for (;;) {
        Py_ssize_t best = -1;
        for (Py_ssize_t r = 0; r < k; r++) {
            if (row_used[r]) {
                continue;
            }
            for (Py_ssize_t c = 0; c < m; c++) {
                double x = d[r * m + c];
                if (!col_used[c] && x <= tol && (best < 0 || x < d[best])) {
                    best = r * m + c;
                }
            }
        }
        if (best < 0) {
            break;
        }
        Py_ssize_t r = best / m, c = best % m;
        row_used[r] = 1;
        col_used[c] = 1;
        out[3 * r] = pts[3 * c];
        out[3 * r + 1] = pts[3 * c + 1];
        out[3 * r + 2] = pts[3 * c + 2];
    }
    result = Py_NewRef(Py_True);
done:
    release(views, 3);
    return result;
}

/* ---- the simulated arm's servo-step inverse kinematics ---------------------------------------- */

/* The six joint frames T_base_from_link_i (i = 0..5) of a UR arm at joint angles q (rad), each as a
 * 3 x 4 row-major [R | t] (mm): the DH matrices of hil.kinematics.ur._joint_frames multiplied in
 * order. dh: per joint d (mm), a (mm), cos(alpha), sin(alpha). */
static void ur_frames(const double *dh, const double *q, double F[6][12])
{
    for (int i = 0; i < 6; i++) {
        double ct = cos(q[i]), st = sin(q[i]);
        double d = dh[4 * i], a = dh[4 * i + 1], ca = dh[4 * i + 2], sa = dh[4 * i + 3];
        double A[12] = {ct, -st * ca, st * sa, a * ct, st, ct * ca, -ct * sa, a * st, 0.0, sa, ca, d};
        if (i == 0) {
            memcpy(F[0], A, sizeof(A));
            continue;
        }
        const double *P = F[i - 1];
        for (int r = 0; r < 3; r++) {
            for (int c = 0; c < 4; c++) {
                double x = P[4 * r] * A[c] + P[4 * r + 1] * A[4 + c] + P[4 * r + 2] * A[8 + c];
                F[i][4 * r + c] = c == 3 ? x + P[4 * r + 3] : x;
            }
        }
    }
}

/* The rotation vector of the rotation matrix m (row-major 3 x 3) as
 * hil.geometry.transform.matrix_to_rotvec computes it: Shepperd's quaternion, normalised, scalar
 * part >= 0, then axis * 2 atan2(|v|, w) (zero below 1e-12). */
static void rotvec_of(const double *m, double *rv)
{
    double m00 = m[0], m01 = m[1], m02 = m[2], m10 = m[3], m11 = m[4], m12 = m[5];
    double m20 = m[6], m21 = m[7], m22 = m[8];
    double tr = m00 + m11 + m22, s, q[4];
    if (tr > 0) {
        s = sqrt(tr + 1.0) * 2.0;
        q[0] = 0.25 * s; q[1] = (m21 - m12) / s; q[2] = (m02 - m20) / s; q[3] = (m10 - m01) / s;
    } else if (m00 > m11 && m00 > m22) {
        s = sqrt(1.0 + m00 - m11 - m22) * 2.0;
        q[0] = (m21 - m12) / s; q[1] = 0.25 * s; q[2] = (m01 + m10) / s; q[3] = (m02 + m20) / s;
    } else if (m11 > m22) {
        s = sqrt(1.0 + m11 - m00 - m22) * 2.0;
        q[0] = (m02 - m20) / s; q[1] = (m01 + m10) / s; q[2] = 0.25 * s; q[3] = (m12 + m21) / s;
    } else {
        s = sqrt(1.0 + m22 - m00 - m11) * 2.0;
        q[0] = (m10 - m01) / s; q[1] = (m02 + m20) / s; q[2] = (m12 + m21) / s; q[3] = 0.25 * s;
    }
    double n = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    double sign = q[0] / n < 0 ? -1.0 : 1.0;   /* normalised first, then the sign (numpy's order) */
    for (int i = 0; i < 4; i++) {
        q[i] = sign * (q[i] / n);
    }
    double w = q[0] > 1.0 ? 1.0 : (q[0] < -1.0 ? -1.0 : q[0]);
    double v = sqrt(q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if (v < 1e-12) {
        rv[0] = rv[1] = rv[2] = 0.0;
        return;
    }
    double angle = 2.0 * atan2(v, w);
    for (int i = 0; i < 3; i++) {
        rv[i] = q[i + 1] / v * angle;
    }
}

/* Solves J x = b (6 x 6, row-major; both destroyed) by Gaussian elimination with partial
 * pivoting; returns the determinant of J (0 when a pivot is exactly 0: x undefined). */
static double solve6(double J[36], double b[6], double x[6])
{
    double det = 1.0;
    for (int c = 0; c < 6; c++) {
        int p = c;
        for (int r = c + 1; r < 6; r++) {
            if (fabs(J[6 * r + c]) > fabs(J[6 * p + c])) {
                p = r;
            }
        }
        if (J[6 * p + c] == 0.0) {
            return 0.0;
        }
        if (p != c) {
            for (int k = 0; k < 6; k++) {
                double t = J[6 * c + k]; J[6 * c + k] = J[6 * p + k]; J[6 * p + k] = t;
            }
            double t = b[c]; b[c] = b[p]; b[p] = t;
            det = -det;
        }
        det *= J[6 * c + c];
        for (int r = c + 1; r < 6; r++) {
            double f = J[6 * r + c] / J[6 * c + c];
            for (int k = c; k < 6; k++) {
                J[6 * r + k] -= f * J[6 * c + k];
            }
            b[r] -= f * b[c];
        }
    }
    for (int r = 5; r >= 0; r--) {
        double acc = b[r];
        for (int k = r + 1; k < 6; k++) {
            acc -= J[6 * r + k] * x[k];
        }
        x[r] = acc / J[6 * r + r];
    }
    return det;
}

PyDoc_STRVAR(ur_newton_doc,
"ur_newton(dh, R, t, q_seed, iterations, tol_mm, tol_rad, min_det, max_jump_rad, q_out) -> int\n\n"
"Newton steps with the geometric Jacobian towards the flange pose (R (3, 3), t (3,) mm) from\n"
"q_seed (6,) rad, as hil.kinematics.ur.ur_newton_ik_numpy: dh (6, 4) is per joint d, a (mm),\n"
"cos(alpha), sin(alpha); all float64 C-contiguous. Returns 0 with the solution in q_out (6,)\n"
"once the pose error is below tol_mm and tol_rad and no joint moved more than max_jump_rad\n"
"from the seed; 1 when it does not get there cleanly (a joint jumped further, |det J| fell below\n"
"min_det (mm^3), or iterations ran out): no solution; -1 when a value was not finite or an\n"
"orientation error was over 2.5 rad (where the rotation vector's axis is ill-defined): the numpy\n"
"code decides. TypeError / ValueError for a bad buffer.");

static int ur_newton_core(const double *dh, const double *Rt, const double *tt, const double *q_seed,
                          int iterations, double tol_mm, double tol_rad, double min_det,
                          double max_jump, double *q_out)
{
    double q[6], F[6][12];
    memcpy(q, q_seed, sizeof(q));
    for (int it = 0; it < iterations; it++) {
        ur_frames(dh, q, F);
        const double *E = F[5];
        double dp[3], m[9], dw[3];
        for (int r = 0; r < 3; r++) {
            dp[r] = tt[r] - E[4 * r + 3];
            for (int c = 0; c < 3; c++) {   /* R_target @ R_e^T */
                m[3 * r + c] = Rt[3 * r] * E[4 * c] + Rt[3 * r + 1] * E[4 * c + 1] + Rt[3 * r + 2] * E[4 * c + 2];
            }
        }
        if (!all_finite(dp, 3) || !all_finite(m, 9)) {
            return -1;
        }
        rotvec_of(m, dw);
        double n_p = sqrt(dp[0] * dp[0] + dp[1] * dp[1] + dp[2] * dp[2]);
        double n_w = sqrt(dw[0] * dw[0] + dw[1] * dw[1] + dw[2] * dw[2]);
        if (n_w > 2.5) {
            return -1;
        }
        if (n_p < tol_mm && n_w < tol_rad) {
            for (int j = 0; j < 6; j++) {
                if (fabs(q[j] - q_seed[j]) > max_jump) {
                    return 1;
                }
            }
            memcpy(q_out, q, sizeof(q));
            return 0;
        }
        double J[36], b[6] = {dp[0], dp[1], dp[2], dw[0], dw[1], dw[2]}, x[6];
        for (int j = 0; j < 6; j++) {   /* column j: axis z_j x (p_e - o_j), then z_j */
            double z[3] = {0.0, 0.0, 1.0}, o[3] = {0.0, 0.0, 0.0};
            if (j > 0) {
                for (int r = 0; r < 3; r++) {
                    z[r] = F[j - 1][4 * r + 2];
                    o[r] = F[j - 1][4 * r + 3];
                }
            }
            double l[3] = {E[3] - o[0], E[7] - o[1], E[11] - o[2]};
            J[j] = z[1] * l[2] - z[2] * l[1];
            J[6 + j] = z[2] * l[0] - z[0] * l[2];
            J[12 + j] = z[0] * l[1] - z[1] * l[0];
            J[18 + j] = z[0];
            J[24 + j] = z[1];
            J[30 + j] = z[2];
        }
        double det = solve6(J, b, x);
        if (!isfinite(det)) {
            return -1;
        }
        if (fabs(det) < min_det) {
            return 1;
        }
        for (int j = 0; j < 6; j++) {
            q[j] += x[j];
        }
        if (!all_finite(q, 6)) {
            return -1;
        }
    }
    return 1;
}

static PyObject *k_ur_newton(PyObject *self, PyObject *args)
{
    PyObject *o_dh, *o_R, *o_t, *o_q, *o_out;
    int iterations;
    double tol_mm, tol_rad, min_det, max_jump;
    if (!PyArg_ParseTuple(args, "OOOOiddddO", &o_dh, &o_R, &o_t, &o_q, &iterations, &tol_mm, &tol_rad,
                          &min_det, &max_jump, &o_out)) {
        return NULL;
    }
    Py_buffer views[5];
    memset(views, 0, sizeof(views));
    PyObject *result = NULL;
    const Py_ssize_t s64[2] = {6, 4}, s33[2] = {3, 3}, s3[1] = {3}, s6[1] = {6};
    const double *dh = get_f64(o_dh, &views[0], "dh", 2, s64, 0);
    const double *R = dh == NULL ? NULL : get_f64(o_R, &views[1], "R", 2, s33, 0);
    const double *t = R == NULL ? NULL : get_f64(o_t, &views[2], "t", 1, s3, 0);
    const double *q = t == NULL ? NULL : get_f64(o_q, &views[3], "q_seed", 1, s6, 0);
    double *out = q == NULL ? NULL : get_f64(o_out, &views[4], "q_out", 1, s6, 1);
    if (out != NULL) {
        int status = -1;
        if (all_finite(dh, 24) && all_finite(R, 9) && all_finite(t, 3) && all_finite(q, 6)) {
            status = ur_newton_core(dh, R, t, q, iterations, tol_mm, tol_rad, min_det, max_jump, out);
        }
        result = PyLong_FromLong(status);
    }
    release(views, 5);
    return result;
}

/* ---- the per-pair control law ------------------------------------------------------------ */

/* C = A B (3 x 3, row-major; C must not alias A or B). */
static void mat3_mul(const double *A, const double *B, double *C)
{
    for (int r = 0; r < 3; r++) {
        for (int c = 0; c < 3; c++) {
            C[3 * r + c] = A[3 * r] * B[c] + A[3 * r + 1] * B[3 + c] + A[3 * r + 2] * B[6 + c];
        }
    }
}

/* The composition (AR, At) @ (BR, Bt) = (AR BR, AR Bt + At) into (CR, Ct) (no aliasing). */
static void rigid_compose(const double *AR, const double *At, const double *BR, const double *Bt,
                          double *CR, double *Ct)
{
    mat3_mul(AR, BR, CR);
    for (int r = 0; r < 3; r++) {
        Ct[r] = AR[3 * r] * Bt[0] + AR[3 * r + 1] * Bt[1] + AR[3 * r + 2] * Bt[2] + At[r];
    }
}

/* Rodrigues, as hil.geometry.transform.rotvec_to_matrix: theta = |rv|; below 1e-12 the identity;
 * else R = I + sin(theta) K + (1 - cos(theta)) K K with K = [rv / theta]x. Returns -1 when theta
 * is not finite (the numpy code decides), else 0. */
static int rodrigues(const double *rv, double *R)
{
    double theta = sqrt(rv[0] * rv[0] + rv[1] * rv[1] + rv[2] * rv[2]);
    if (!isfinite(theta)) {
        return -1;
    }
    for (int i = 0; i < 9; i++) {
        R[i] = (i % 4 == 0) ? 1.0 : 0.0;
    }
    if (theta < 1e-12) {
        return 0;
    }
    double k0 = rv[0] / theta, k1 = rv[1] / theta, k2 = rv[2] / theta;
    double K[9] = {0.0, -k2, k1, k2, 0.0, -k0, -k1, k0, 0.0}, KK[9];
    mat3_mul(K, K, KK);
    double s = sin(theta), c1 = 1.0 - cos(theta);
    for (int i = 0; i < 9; i++) {
        R[i] = R[i] + s * K[i] + c1 * KK[i];
    }
    return 0;
}

/* The pose of the motion filter's 6-vector y = x + v h (t mm, rotation vector rad). */
static int filter_pose_core(const double *x, const double *v, double h, double *R, double *t)
{
    double y[6];
    for (int i = 0; i < 6; i++) {
        y[i] = x[i] + v[i] * h;
    }
    if (!all_finite(y, 6) || rodrigues(y + 3, R) != 0) {
        return -1;
    }
    memcpy(t, y, 3 * sizeof(double));
    return 0;
}

PyDoc_STRVAR(filter_feed_doc,
"filter_feed(R, t, Rc, tc, x, v, dt_s, alpha, beta) -> int\n\n"
"One alpha-beta step of hil.controller.compensation.MotionFilter for the measured change (R (3, 3),\n"
"t (3,) mm, optical frame) expressed about the centre (Rc, tc): z = [t', rotvec(R')] of\n"
"(Rc, tc)^-1 @ (R, t) @ (Rc, tc); x_pred = x + v dt_s; r = z - x_pred; x = x_pred + alpha r;\n"
"v = v + (beta / dt_s) r, written into x (6,) and v (6,) in place. dt_s > 0. Returns 0, or -1\n"
"(x and v unchanged) when a value is not finite: the numpy code decides. TypeError / ValueError\n"
"for a bad buffer.");

static PyObject *k_filter_feed(PyObject *self, PyObject *args)
{
    static const BufSpec spec[6] = {{"R", 2, {3, 3}, 0}, {"t", 1, {3}, 0}, {"Rc", 2, {3, 3}, 0},
                                    {"tc", 1, {3}, 0}, {"x", 1, {6}, 1}, {"v", 1, {6}, 1}};
    PyObject *o[6];
    double dt, alpha, beta, *p[6];
    if (!PyArg_ParseTuple(args, "OOOOOOddd", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &dt, &alpha, &beta)) {
        return NULL;
    }
    Py_buffer views[6];
    PyObject *result = NULL;
    if (get_all(o, spec, 6, views, p) == 0) {
        const double *R = p[0], *t = p[1], *Rc = p[2], *tc = p[3];
        double *x = p[4], *v = p[5];
        int status = -1;
        if (all_finite(R, 9) && all_finite(t, 3) && all_finite(Rc, 9) && all_finite(tc, 3)
                && all_finite(x, 6) && all_finite(v, 6) && isfinite(dt) && dt > 0.0) {
            double RcT[9], mtc[3], AR[9], At[3], BR[9], Bt[3], z[6], xn[6], vn[6];
            for (int r = 0; r < 3; r++) {   /* (Rc, tc)^-1 = (Rc^T, -Rc^T tc) */
                for (int c = 0; c < 3; c++) {
                    RcT[3 * r + c] = Rc[3 * c + r];
                }
            }
            for (int r = 0; r < 3; r++) {
                mtc[r] = -RcT[3 * r] * tc[0] - RcT[3 * r + 1] * tc[1] - RcT[3 * r + 2] * tc[2];
            }
            rigid_compose(RcT, mtc, R, t, AR, At);
            rigid_compose(AR, At, Rc, tc, BR, Bt);
            memcpy(z, Bt, sizeof(Bt));
            rotvec_of(BR, z + 3);
            double g = beta / dt;
            for (int i = 0; i < 6; i++) {
                double x_pred = x[i] + v[i] * dt, r = z[i] - x_pred;
                xn[i] = x_pred + alpha * r;
                vn[i] = v[i] + g * r;
            }
            if (all_finite(xn, 6) && all_finite(vn, 6)) {
                memcpy(x, xn, sizeof(xn));
                memcpy(v, vn, sizeof(vn));
                status = 0;
            }
        }
        result = PyLong_FromLong(status);
    }
    release(views, 6);
    return result;
}

PyDoc_STRVAR(filter_pose_doc,
"filter_pose(x, v, h_s, R_out, t_out) -> int\n\n"
"The pose of the motion filter's state extrapolated by h_s: y = x + v h_s (6,: t mm, rotation\n"
"vector rad), R_out (3, 3) = Rodrigues(y[3:]) as hil.geometry.transform.rotvec_to_matrix,\n"
"t_out (3,) = y[:3]. Returns 0, or -1 when a value is not finite (the numpy code decides).\n"
"TypeError / ValueError for a bad buffer.");

static PyObject *k_filter_pose(PyObject *self, PyObject *args)
{
    static const BufSpec spec[4] = {{"x", 1, {6}, 0}, {"v", 1, {6}, 0}, {"R_out", 2, {3, 3}, 1},
                                    {"t_out", 1, {3}, 1}};
    PyObject *o[4];
    double h, *p[4];
    if (!PyArg_ParseTuple(args, "OOdOO", &o[0], &o[1], &h, &o[2], &o[3])) {
        return NULL;
    }
    Py_buffer views[4];
    PyObject *result = NULL;
    if (get_all(o, spec, 4, views, p) == 0) {
        result = PyLong_FromLong(filter_pose_core(p[0], p[1], h, p[2], p[3]));
    }
    release(views, 4);
    return result;
}

PyDoc_STRVAR(tcp_setpoint_doc,
"tcp_setpoint(x, v, h0_s, h1_s, dt_s, LR, Lt, RR, Rt, R_out, t_out, vel_out, w_out) -> int\n\n"
"The tracking setpoint of hil.controller.estimate.Estimate.tracking_setpoint: D0 = L @ X0 @ Rr\n"
"with X0 the filter's pose at h0_s (filter_pose), written into R_out (3, 3) and t_out (3,) mm;\n"
"with dt_s > 0 also D1 = L @ X1 @ Rr at h1_s, vel_out (3,) = (D1.t - D0.t) / dt_s mm/s and\n"
"w_out (3,) = rotvec(D1.R D0.R^T) / dt_s rad/s, else both zero. L = (LR, Lt), Rr = (RR, Rt) are\n"
"the chain's outer transforms. Returns 0, or -1 when a value is not finite (the numpy code\n"
"decides). TypeError / ValueError for a bad buffer.");

static int tcp_setpoint_core(const double *x, const double *v, double h0, double h1, double dt,
                             const double *LR, const double *Lt, const double *RR, const double *Rt,
                             double *R_out, double *t_out, double *vel, double *w)
{
    double XR[9], Xt[3], AR[9], At[3], D0R[9], D0t[3];
    if (filter_pose_core(x, v, h0, XR, Xt) != 0) {
        return -1;
    }
    rigid_compose(LR, Lt, XR, Xt, AR, At);
    rigid_compose(AR, At, RR, Rt, D0R, D0t);
    double dv[3] = {0.0, 0.0, 0.0}, dw[3] = {0.0, 0.0, 0.0};
    if (dt > 0.0) {
        double D1R[9], D1t[3], D0RT[9], M[9];
        if (filter_pose_core(x, v, h1, XR, Xt) != 0) {
            return -1;
        }
        rigid_compose(LR, Lt, XR, Xt, AR, At);
        rigid_compose(AR, At, RR, Rt, D1R, D1t);
        for (int r = 0; r < 3; r++) {
            dv[r] = (D1t[r] - D0t[r]) / dt;
            for (int c = 0; c < 3; c++) {
                D0RT[3 * r + c] = D0R[3 * c + r];
            }
        }
        mat3_mul(D1R, D0RT, M);
        rotvec_of(M, dw);
        for (int r = 0; r < 3; r++) {
            dw[r] = dw[r] / dt;
        }
    }
    if (!all_finite(D0R, 9) || !all_finite(D0t, 3) || !all_finite(dv, 3) || !all_finite(dw, 3)) {
        return -1;
    }
    memcpy(R_out, D0R, sizeof(D0R));
    memcpy(t_out, D0t, sizeof(D0t));
    memcpy(vel, dv, sizeof(dv));
    memcpy(w, dw, sizeof(dw));
    return 0;
}

static PyObject *k_tcp_setpoint(PyObject *self, PyObject *args)
{
    static const BufSpec spec[10] = {
        {"x", 1, {6}, 0}, {"v", 1, {6}, 0}, {"LR", 2, {3, 3}, 0}, {"Lt", 1, {3}, 0},
        {"RR", 2, {3, 3}, 0}, {"Rt", 1, {3}, 0}, {"R_out", 2, {3, 3}, 1}, {"t_out", 1, {3}, 1},
        {"vel_out", 1, {3}, 1}, {"w_out", 1, {3}, 1}};
    PyObject *o[10];
    double h0, h1, dt, *p[10];
    if (!PyArg_ParseTuple(args, "OOdddOOOOOOOO", &o[0], &o[1], &h0, &h1, &dt, &o[2], &o[3], &o[4], &o[5],
                          &o[6], &o[7], &o[8], &o[9])) {
        return NULL;
    }
    Py_buffer views[10];
    PyObject *result = NULL;
    if (get_all(o, spec, 10, views, p) == 0) {
        int status = -1;
        if (all_finite(p[2], 9) && all_finite(p[3], 3) && all_finite(p[4], 9) && all_finite(p[5], 3)
                && isfinite(h0) && isfinite(h1) && isfinite(dt)) {
            status = tcp_setpoint_core(p[0], p[1], h0, h1, dt, p[2], p[3], p[4], p[5], p[6], p[7], p[8],
                                       p[9]);
        }
        result = PyLong_FromLong(status);
    }
    release(views, 10);
    return result;
}

/* ---- the sliding-window AR predictor (hil.prediction.ar.ArModel) ---------------------------- */

/* The AR model's state, in arrays the Python side owns (hil/prediction/ar.py, "compiled"):
 *   ring (C, 3): the last C = N + p + 1 increments, a ring; meta (4,): head (index of the newest
 *   increment), increments held, samples seen (0, 1 or more), rows in the normal equations;
 *   A (3, p*p), b (3, p): each axis's running normal equations; a (3, p): its coefficients;
 *   y (3,): the last sample. Counters are whole numbers stored as float64 (exact below 2^53). */

/* The j-th newest increment (j = 0: newest), axis c. */
static double ar_inc(const double *ring, Py_ssize_t cap, Py_ssize_t head, Py_ssize_t j, int c)
{
    Py_ssize_t i = (head - j) % cap;
    if (i < 0) {
        i += cap;
    }
    return ring[3 * i + c];
}

/* Add (sign +1) or remove (-1) the row whose target is the k-th newest increment: regressors the
 * p increments before it, newest first (ArModel._row). */
static void ar_row(double *A, double *b, const double *ring, Py_ssize_t cap, Py_ssize_t head, int p,
                   Py_ssize_t k, double sign)
{
    for (int c = 0; c < 3; c++) {
        double phi[64];
        double tgt = ar_inc(ring, cap, head, k, c);
        for (int i = 0; i < p; i++) {
            phi[i] = ar_inc(ring, cap, head, k + 1 + i, c);
        }
        for (int i = 0; i < p; i++) {
            for (int j = 0; j < p; j++) {
                A[c * p * p + i * p + j] += sign * phi[i] * phi[j];
            }
            b[c * p + i] += sign * phi[i] * tgt;
        }
    }
}

/* Solve (A_c + ridge I) a_c = b_c for each axis by Gaussian elimination with partial pivoting.
 * 0, or -1 (a singular or non-finite system: ``a`` is left as it was). */
static int ar_solve(const double *A, const double *b, double ridge, int p, double *a)
{
    double out[3][64];
    for (int c = 0; c < 3; c++) {
        double m[64][65];
        for (int i = 0; i < p; i++) {
            for (int j = 0; j < p; j++) {
                m[i][j] = A[c * p * p + i * p + j] + (i == j ? ridge : 0.0);
            }
            m[i][p] = b[c * p + i];
        }
        for (int col = 0; col < p; col++) {
            int piv = col;
            for (int r = col + 1; r < p; r++) {
                if (fabs(m[r][col]) > fabs(m[piv][col])) {
                    piv = r;
                }
            }
            if (!(fabs(m[piv][col]) > 0.0) || !isfinite(m[piv][col])) {
                return -1;
            }
            if (piv != col) {
                for (int j = col; j <= p; j++) {
                    double t = m[col][j];
                    m[col][j] = m[piv][j];
                    m[piv][j] = t;
                }
            }
            for (int r = col + 1; r < p; r++) {
                double f = m[r][col] / m[col][col];
                for (int j = col; j <= p; j++) {
                    m[r][j] -= f * m[col][j];
                }
            }
        }
        for (int i = p - 1; i >= 0; i--) {
            double acc = m[i][p];
            for (int j = i + 1; j < p; j++) {
                acc -= m[i][j] * out[c][j];
            }
            out[c][i] = acc / m[i][i];
        }
        if (!all_finite(out[c], p)) {
            return -1;
        }
    }
    for (int c = 0; c < 3; c++) {
        memcpy(a + c * p, out[c], (size_t)p * sizeof(double));
    }
    return 0;
}

PyDoc_STRVAR(ar_feed_doc,
"ar_feed(x, ring, A, b, a, y, meta, order, window, ridge) -> int\n\n"
"One sample x (3,) mm into the AR model's state (hil.prediction.ar.ArModel.feed): its increment\n"
"into the ring, the newest row added to each axis's normal equations and the row leaving the\n"
"window removed, the coefficients solved once the window is full. 0; -1 when the solve failed\n"
"(the coefficients are unchanged: the caller refits with numpy, which raises). order <= 64.");

static PyObject *k_ar_feed(PyObject *self, PyObject *args)
{
    static const BufSpec spec[7] = {
        {"x", 1, {3}, 0}, {"ring", 2, {-1, 3}, 1}, {"A", 2, {3, -1}, 1}, {"b", 2, {3, -1}, 1},
        {"a", 2, {3, -1}, 1}, {"y", 1, {3}, 1}, {"meta", 1, {4}, 1}};
    PyObject *o[7];
    int p, n;
    double ridge, *q[7];
    if (!PyArg_ParseTuple(args, "OOOOOOOiid", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &p, &n,
                          &ridge)) {
        return NULL;
    }
    Py_buffer views[7];
    PyObject *result = NULL;
    if (get_all(o, spec, 7, views, q) == 0) {
        Py_ssize_t cap = views[1].shape[0];
        if (p < 1 || p > 64 || n <= p || cap != (Py_ssize_t)n + p + 1 || views[2].shape[1] != (Py_ssize_t)p * p
                || views[3].shape[1] != p || views[4].shape[1] != p) {
            PyErr_SetString(PyExc_ValueError, "ar_feed: shapes do not match order and window");
        } else {
            double *ring = q[1], *A = q[2], *b = q[3], *a = q[4], *y = q[5], *meta = q[6];
            Py_ssize_t head = (Py_ssize_t)meta[0], held = (Py_ssize_t)meta[1], rows = (Py_ssize_t)meta[3];
            int status = 0;
            if (meta[2] > 0.0) {
                head = (head + 1) % cap;
                for (int c = 0; c < 3; c++) {
                    ring[3 * head + c] = q[0][c] - y[c];
                }
                held = held < cap ? held + 1 : cap;
            }
            memcpy(y, q[0], 3 * sizeof(double));
            meta[2] = meta[2] < 2.0 ? meta[2] + 1.0 : 2.0;
            if (held > p) {
                ar_row(A, b, ring, cap, head, p, 0, 1.0);
                rows += 1;
                if (rows > n) {
                    ar_row(A, b, ring, cap, head, p, n, -1.0);
                    rows = n;
                }
                if (rows >= n) {
                    status = ar_solve(A, b, ridge, p, a);
                }
            }
            meta[0] = (double)head;
            meta[1] = (double)held;
            meta[3] = (double)rows;
            result = PyLong_FromLong(status);
        }
    }
    release(views, 7);
    return result;
}

PyDoc_STRVAR(ar_forecast_doc,
"ar_forecast(steps, ring, a, y, meta, order, out) -> None\n\n"
"The AR model's forecast ``steps`` samples after the last (hil.prediction.ar.ArModel.forecast):\n"
"the one-step model iterated, a fractional step linear between its whole neighbours; into\n"
"out (3,) mm. The model must be ready (the window full).");

static PyObject *k_ar_forecast(PyObject *self, PyObject *args)
{
    static const BufSpec spec[5] = {
        {"ring", 2, {-1, 3}, 0}, {"a", 2, {3, -1}, 0}, {"y", 1, {3}, 0}, {"meta", 1, {4}, 0},
        {"out", 1, {3}, 1}};
    PyObject *o[5];
    int p;
    double steps, *q[5];
    if (!PyArg_ParseTuple(args, "dOOOOiO", &steps, &o[0], &o[1], &o[2], &o[3], &p, &o[4])) {
        return NULL;
    }
    Py_buffer views[5];
    PyObject *result = NULL;
    if (get_all(o, spec, 5, views, q) == 0) {
        Py_ssize_t cap = views[0].shape[0];
        if (p < 1 || p > 64 || views[1].shape[1] != p || q[3][1] < p || !isfinite(steps)) {
            PyErr_SetString(PyExc_ValueError, "ar_forecast: shapes do not match order, or too few increments");
        } else {
            const double *ring = q[0], *a = q[1];
            Py_ssize_t head = (Py_ssize_t)q[3][0];
            double s = steps > 0.0 ? steps : 0.0;
            long hi = (long)ceil(s);
            for (int c = 0; c < 3; c++) {
                double reg[64], y = q[2][c], prev = y, inc = 0.0, res = y;
                for (int i = 0; i < p; i++) {
                    reg[i] = ar_inc(ring, cap, head, i, c);
                }
                for (long k = 1; k <= hi; k++) {
                    inc = 0.0;
                    for (int i = 0; i < p; i++) {
                        inc += a[c * p + i] * reg[i];
                    }
                    prev = y;
                    y = y + inc;
                    memmove(reg + 1, reg, (size_t)(p - 1) * sizeof(double));
                    reg[0] = inc;
                }
                res = (hi >= 1 && s < (double)hi) ? prev + (s - (double)(hi - 1)) * inc : y;
                q[4][c] = res;
            }
            Py_INCREF(Py_None);
            result = Py_None;
        }
    }
    release(views, 5);
    return result;
}

/* ---- the surrogate target model ------------------------------------------------------------- */

#define TARGET_MAX_MARKERS 64   /* more seen markers go the numpy way */
#define MIN_PATH_MM 1.0          /* hil.controller.target_model.MIN_PATH_MM */

/* y = M x, M row-major 3 x 3 */
static void mat3_vec(const double *M, const double *x, double *y)
{
    for (int j = 0; j < 3; j++) {
        y[j] = M[3 * j] * x[0] + M[3 * j + 1] * x[1] + M[3 * j + 2] * x[2];
    }
}

/* y = M^T x, M row-major 3 x 3 */
static void mat3t_vec(const double *M, const double *x, double *y)
{
    for (int j = 0; j < 3; j++) {
        y[j] = M[j] * x[0] + M[3 + j] * x[1] + M[6 + j] * x[2];
    }
}

/* Whether rows i of a and b (n x 3) are both finite: the marker was registered and is seen. */
static int row_seen(const double *a, const double *b, Py_ssize_t i)
{
    for (int j = 0; j < 3; j++) {
        if (!isfinite(a[3 * i + j]) || !isfinite(b[3 * i + j])) {
            return 0;
        }
    }
    return 1;
}

/* The (N, 3) arrays of a target call after the first: the same N rows as the first. */
static int same_rows(Py_buffer *views, int first, int count, const char *call)
{
    for (int i = first; i < first + count; i++) {
        if (views[i].shape[0] != views[0].shape[0]) {
            PyErr_Format(PyExc_ValueError, "%s: argument %d has %zd rows, the reference %zd", call, i + 1,
                         views[i].shape[0], views[0].shape[0]);
            return -1;
        }
    }
    return 0;
}

PyDoc_STRVAR(target_score_doc,
"target_score(reference, live, pattern, R_oi, out) -> int\n\n"
"The surrogate target model's breathing score (hil.controller.target_model, the numpy reference\n"
"score_parts_numpy): reference, live (N, 3) optical frame mm, NaN rows not seen;\n"
"pattern (N, 3) the model's unit pattern u (image frame); R_oi (3, 3) R_optical_from_image.\n"
"With d_i = R_oi^T (live_i - reference_i) over the seen rows: writes out (3,) = [z = u.d / share\n"
"(mm), share = |u_seen|^2, sqrt(|d - z u|^2 / seen) (mm)], z and the residual NaN when share is\n"
"0. Returns the number of seen rows. TypeError / ValueError for a bad buffer.");

static PyObject *k_target_score(PyObject *self, PyObject *args)
{
    static const BufSpec spec[5] = {{"reference", 2, {-1, 3}, 0}, {"live", 2, {-1, 3}, 0},
                                    {"pattern", 2, {-1, 3}, 0}, {"R_oi", 2, {3, 3}, 0}, {"out", 1, {3}, 1}};
    PyObject *o[5];
    double *q[5];
    if (!PyArg_ParseTuple(args, "OOOOO", &o[0], &o[1], &o[2], &o[3], &o[4])) {
        return NULL;
    }
    Py_buffer views[5];
    PyObject *result = NULL;
    if (get_all(o, spec, 5, views, q) == 0 && same_rows(views, 1, 2, "target_score") == 0) {
        const double *ref = q[0], *live = q[1], *u = q[2], *R_oi = q[3];
        Py_ssize_t n = views[0].shape[0], seen = 0;
        double share = 0.0, ud = 0.0;
        for (Py_ssize_t i = 0; i < n; i++) {   /* share, u . d: index order (numpy: to rounding) */
            if (!row_seen(ref, live, i)) {
                continue;
            }
            seen++;
            double m[3] = {live[3 * i] - ref[3 * i], live[3 * i + 1] - ref[3 * i + 1],
                           live[3 * i + 2] - ref[3 * i + 2]}, d[3];
            mat3t_vec(R_oi, m, d);
            for (int j = 0; j < 3; j++) {
                share += u[3 * i + j] * u[3 * i + j];
                ud += u[3 * i + j] * d[j];
            }
        }
        double z = share > 0.0 ? ud / share : NAN, r2 = 0.0;
        for (Py_ssize_t i = 0; i < n && share > 0.0; i++) {
            if (!row_seen(ref, live, i)) {
                continue;
            }
            double m[3] = {live[3 * i] - ref[3 * i], live[3 * i + 1] - ref[3 * i + 1],
                           live[3 * i + 2] - ref[3 * i + 2]}, d[3];
            mat3t_vec(R_oi, m, d);
            for (int j = 0; j < 3; j++) {
                double e = d[j] - z * u[3 * i + j];
                r2 += e * e;
            }
        }
        q[4][0] = z;
        q[4][1] = share;
        q[4][2] = share > 0.0 ? sqrt(r2 / (double)seen) : NAN;
        result = PyLong_FromSsize_t(seen);
    }
    release(views, 5);
    return result;
}

PyDoc_STRVAR(target_turn_doc,
"target_turn(reference, live, pattern, R_oi, t_oi, entry, target, a, b, R_change, t_change, z,\n"
"            rate, out) -> int\n\n"
"The path's turn at the modelled target (hil.controller.target_model, the numpy reference\n"
"turn_numpy). reference, live, pattern (N, 3) as target_score; R_oi (3, 3), t_oi (3,)\n"
"T_optical_from_image; entry, target (3,) the plan's (image frame, mm); a, b (3,) the target per\n"
"mm of score and per mm/s of rate; R_change (3, 3), t_change (3,) the estimator's\n"
"T_live_from_ref; z (mm), rate (mm/s). The target z a + rate b from the plan's, moved by the\n"
"seen rows' mean of live - reference - z R_oi u (what the markers moved beyond the pattern);\n"
"d0 the changed planned direction, d1 from the changed entry to the moved target. Writes out\n"
"(5,) = [rotation vector of the smallest rotation taking d0 onto d1 (3, rad), its angle\n"
"atan2(|d0 x d1|, d0 . d1) (deg), |z a + rate b| (mm)]. Returns 0; -1 (out undefined) when the\n"
"numpy code must decide: no row seen, z or rate not finite, or a path shorter than 1 mm (from\n"
"the entry to the target, planned or modelled). TypeError / ValueError for a bad buffer.");

static PyObject *k_target_turn(PyObject *self, PyObject *args)
{
    static const BufSpec spec[12] = {
        {"reference", 2, {-1, 3}, 0}, {"live", 2, {-1, 3}, 0}, {"pattern", 2, {-1, 3}, 0},
        {"R_oi", 2, {3, 3}, 0}, {"t_oi", 1, {3}, 0}, {"entry", 1, {3}, 0}, {"target", 1, {3}, 0},
        {"a", 1, {3}, 0}, {"b", 1, {3}, 0}, {"R_change", 2, {3, 3}, 0}, {"t_change", 1, {3}, 0},
        {"out", 1, {5}, 1}};
    PyObject *o[12];
    double *q[12], z, rate;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOddO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7],
                          &o[8], &o[9], &o[10], &z, &rate, &o[11])) {
        return NULL;
    }
    Py_buffer views[12];
    PyObject *result = NULL;
    if (get_all(o, spec, 12, views, q) != 0 || same_rows(views, 1, 2, "target_turn") != 0) {
        goto done;
    }
    const double *ref = q[0], *live = q[1], *u = q[2], *R_oi = q[3], *t_oi = q[4];
    const double *Rc = q[9], *tc = q[10];
    double *out = q[11];
    Py_ssize_t n = views[0].shape[0], k = 0;
    double other[3] = {0.0, 0.0, 0.0};
    for (Py_ssize_t i = 0; i < n; i++) {   /* the seen rows' mean displacement beyond the pattern */
        if (!row_seen(ref, live, i)) {
            continue;
        }
        double du[3];
        mat3_vec(R_oi, u + 3 * i, du);
        for (int j = 0; j < 3; j++) {
            other[j] += live[3 * i + j] - ref[3 * i + j] - z * du[j];
        }
        k++;
    }
    if (k == 0 || !isfinite(z) || !isfinite(rate)) {
        result = PyLong_FromLong(-1);
        goto done;
    }
    double entry_ref[3], target_ref[3], shift[3], shift_o[3], target_live[3], entry_live[3];
    mat3_vec(R_oi, q[5], entry_ref);
    mat3_vec(R_oi, q[6], target_ref);
    for (int j = 0; j < 3; j++) {
        entry_ref[j] += t_oi[j];
        target_ref[j] += t_oi[j];
        shift[j] = z * q[7][j] + rate * q[8][j];
    }
    mat3_vec(R_oi, shift, shift_o);
    mat3_vec(Rc, entry_ref, entry_live);
    for (int j = 0; j < 3; j++) {   /* the modelled target, moved with what breathing leaves */
        target_live[j] = target_ref[j] + shift_o[j] + other[j] / (double)k;
    }
    double planned[3], d0[3], d1[3];
    for (int j = 0; j < 3; j++) {
        entry_live[j] += tc[j];
        planned[j] = target_ref[j] - entry_ref[j];
    }
    mat3_vec(Rc, planned, d0);
    for (int j = 0; j < 3; j++) {
        d1[j] = target_live[j] - entry_live[j];
    }
    double n0 = sqrt(d0[0] * d0[0] + d0[1] * d0[1] + d0[2] * d0[2]);
    double n1 = sqrt(d1[0] * d1[0] + d1[1] * d1[1] + d1[2] * d1[2]);
    if (!(n0 >= MIN_PATH_MM) || !(n1 >= MIN_PATH_MM) || !isfinite(n0) || !isfinite(n1)) {
        result = PyLong_FromLong(-1);
        goto done;
    }
    for (int j = 0; j < 3; j++) {
        d0[j] /= n0;
        d1[j] /= n1;
    }
    double c = d0[0] * d1[0] + d0[1] * d1[1] + d0[2] * d1[2];
    c = c < -1.0 ? -1.0 : (c > 1.0 ? 1.0 : c);
    double axis[3] = {d0[1] * d1[2] - d0[2] * d1[1], d0[2] * d1[0] - d0[0] * d1[2],
                      d0[0] * d1[1] - d0[1] * d1[0]};
    double s = sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]);
    double angle = atan2(s, c);
    for (int j = 0; j < 3; j++) {
        out[j] = s < 1e-12 ? 0.0 : axis[j] / s * angle;
    }
    out[3] = angle * (180.0 / 3.14159265358979323846);   /* atan2: exact near 0, unlike acos */
    out[4] = sqrt(shift[0] * shift[0] + shift[1] * shift[1] + shift[2] * shift[2]);
    result = PyLong_FromLong(0);
done:
    release(views, 12);
    return result;
}

PyDoc_STRVAR(turn_about_doc,
"turn_about(rotvec, weight, R_change, t_change, R_oi, t_oi, entry, R_out, t_out) -> None\n\n"
"The change T_live_from_ref (R_change (3, 3), t_change (3,)) turned by weight * rotvec (rad,\n"
"(3,)) about the changed entry (hil.controller.target_model.TargetTracker.steer): R = exp(weight\n"
"rotvec) R_change (Rodrigues, as hil.geometry.transform.rotvec_to_matrix), and t such that the\n"
"entry (3,) image frame, through R_oi (3, 3), t_oi (3,) T_optical_from_image, lands where the\n"
"change puts it. Writes R_out (3, 3), t_out (3,). ValueError for a weight or rotation vector\n"
"that is not finite; TypeError / ValueError for a bad buffer.");

static PyObject *k_turn_about(PyObject *self, PyObject *args)
{
    static const BufSpec spec[8] = {
        {"rotvec", 1, {3}, 0}, {"R_change", 2, {3, 3}, 0}, {"t_change", 1, {3}, 0}, {"R_oi", 2, {3, 3}, 0},
        {"t_oi", 1, {3}, 0}, {"entry", 1, {3}, 0}, {"R_out", 2, {3, 3}, 1}, {"t_out", 1, {3}, 1}};
    PyObject *o[8];
    double *q[8], weight;
    if (!PyArg_ParseTuple(args, "OdOOOOOOO", &o[0], &weight, &o[1], &o[2], &o[3], &o[4], &o[5], &o[6],
                          &o[7])) {
        return NULL;
    }
    Py_buffer views[8];
    PyObject *result = NULL;
    if (get_all(o, spec, 8, views, q) != 0) {
        goto done;
    }
    double v[3] = {weight * q[0][0], weight * q[0][1], weight * q[0][2]};
    if (!isfinite(v[0]) || !isfinite(v[1]) || !isfinite(v[2])) {
        PyErr_SetString(PyExc_ValueError, "turn_about: the weighted rotation vector is not finite");
        goto done;
    }
    double theta = hypot(hypot(v[0], v[1]), v[2]);
    double Rt[9] = {1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0};
    if (theta >= 1e-12) {   /* I + sin(theta) K + (1 - cos(theta)) K^2, K = skew(v / theta) */
        double kx = v[0] / theta, ky = v[1] / theta, kz = v[2] / theta;
        double K[9] = {0.0, -kz, ky, kz, 0.0, -kx, -ky, kx, 0.0};
        double sn = sin(theta), cs = 1.0 - cos(theta);
        for (int i = 0; i < 3; i++) {
            for (int j = 0; j < 3; j++) {
                double kk = K[3 * i] * K[j] + K[3 * i + 1] * K[3 + j] + K[3 * i + 2] * K[6 + j];
                Rt[3 * i + j] += sn * K[3 * i + j] + cs * kk;
            }
        }
    }
    const double *Rc = q[1], *tc = q[2];
    double *R = q[6], *t = q[7];
    for (int i = 0; i < 3; i++) {
        for (int j = 0; j < 3; j++) {
            R[3 * i + j] = Rt[3 * i] * Rc[j] + Rt[3 * i + 1] * Rc[3 + j] + Rt[3 * i + 2] * Rc[6 + j];
        }
    }
    double entry_ref[3], entry_live[3], Re[3];
    mat3_vec(q[3], q[5], entry_ref);
    for (int j = 0; j < 3; j++) {
        entry_ref[j] += q[4][j];
    }
    mat3_vec(Rc, entry_ref, entry_live);
    mat3_vec(R, entry_ref, Re);
    for (int j = 0; j < 3; j++) {   /* t = entry_live - R entry_ref */
        t[j] = entry_live[j] + tc[j] - Re[j];
    }
    Py_INCREF(Py_None);
    result = Py_None;
done:
    release(views, 8);
    return result;
}

/* ---- the local change estimators ------------------------------------------------------------ */

PyDoc_STRVAR(local_change_doc,
"local_change(reference, live, entry, sigma_mm, min_share, tps_row, R_out, t_out, t_tps_out) -> int\n\n"
"The 'weighted' change estimator and, with a spline row, 'local-tps' (hil.controller.\n"
"change_estimate, the numpy reference weighted_numpy and tps_numpy): reference, live (N, 3) the\n"
"seen markers (optical frame, mm); entry (3,) mm. Weights w_i = exp(-(|r_i - entry| / sigma)^2),\n"
"those below min_share times the largest set to 0; Horn's fit of the reference onto the live\n"
"markers with those weights writes R_out (3, 3), t_out (3,). tps_row (N,) float64 or None: the\n"
"thin-plate spline's row at the entry; with it, t_tps_out (3,) = t_out + sum_i tps_row_i (live_i\n"
"- R reference_i - t) (the same rotation; 'local-tps'), else t_tps_out is untouched. Returns the\n"
"markers kept (>= 3); 0 when fewer than 3 keep a weight; -1 (outputs undefined) when the fit\n"
"declines (registration.py's checks, horn's doc): the numpy code decides. sigma_mm must be\n"
"positive. TypeError / ValueError for a bad buffer.");

static PyObject *k_local_change(PyObject *self, PyObject *args)
{
    static const BufSpec spec[6] = {
        {"reference", 2, {-1, 3}, 0}, {"live", 2, {-1, 3}, 0}, {"entry", 1, {3}, 0},
        {"R_out", 2, {3, 3}, 1}, {"t_out", 1, {3}, 1}, {"t_tps_out", 1, {3}, 1}};
    PyObject *o[6], *o_row;
    double *q[6], sigma, min_share;
    if (!PyArg_ParseTuple(args, "OOOddOOOO", &o[0], &o[1], &o[2], &sigma, &min_share, &o_row, &o[3], &o[4],
                          &o[5])) {
        return NULL;
    }
    Py_buffer views[7];
    PyObject *result = NULL;
    memset(&views[6], 0, sizeof(Py_buffer));
    if (get_all(o, spec, 6, views, q) != 0 || same_rows(views, 1, 1, "local_change") != 0) {
        goto done;
    }
    Py_ssize_t n = views[0].shape[0];
    const Py_ssize_t sn[1] = {n};
    const double *row = NULL;
    if (o_row != Py_None && (row = get_f64(o_row, &views[6], "tps_row", 1, sn, 0)) == NULL) {
        goto done;
    }
    if (!(sigma > 0.0) || !isfinite(sigma) || n > TARGET_MAX_MARKERS) {
        if (!(sigma > 0.0) || !isfinite(sigma)) {
            PyErr_SetString(PyExc_ValueError, "local_change: sigma_mm must be positive and finite");
        } else {
            result = PyLong_FromLong(-1);
        }
        goto done;
    }
    const double *ref = q[0], *live = q[1], *entry = q[2];
    double w[TARGET_MAX_MARKERS], res[TARGET_MAX_MARKERS], w_max = 0.0;
    for (Py_ssize_t i = 0; i < n; i++) {   /* entry_weights */
        double d2 = 0.0;
        for (int j = 0; j < 3; j++) {
            double d = ref[3 * i + j] - entry[j];
            d2 += d * d;
        }
        w[i] = exp(-d2 / (sigma * sigma));
        w_max = w[i] > w_max ? w[i] : w_max;
    }
    Py_ssize_t kept = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (w[i] >= min_share * w_max && isfinite(w[i])) {
            kept++;
        } else {
            w[i] = 0.0;
        }
    }
    if (kept < 3) {
        result = PyLong_FromLong(0);
        goto done;
    }
    double *R = q[3], *t = q[4];
    if (horn_solve(live, ref, w, n, R, t, res) < 0.0) {
        result = PyLong_FromLong(-1);
        goto done;
    }
    if (row != NULL) {
        double delta[3] = {0.0, 0.0, 0.0};
        for (Py_ssize_t i = 0; i < n; i++) {
            double pred[3];
            mat3_vec(R, ref + 3 * i, pred);
            for (int j = 0; j < 3; j++) {
                delta[j] += row[i] * (live[3 * i + j] - (pred[j] + t[j]));
            }
        }
        for (int j = 0; j < 3; j++) {
            q[5][j] = t[j] + delta[j];
        }
        if (!all_finite(q[5], 3)) {
            result = PyLong_FromLong(-1);
            goto done;
        }
    }
    result = PyLong_FromSsize_t(kept);
done:
    release(views, 7);
    return result;
}

/* ---- the pattern estimator's entry ------------------------------------------------------------ */

PyDoc_STRVAR(pattern_entry_doc,
"pattern_entry(P6, E, Q, reference, live, entry, out) -> int\n\n"
"The 'pattern' estimator's entry (hil.controller.entry_pattern, the numpy reference\n"
"entry_numpy): reference, live (N, 3) the seen markers (optical frame, mm); entry (3,) mm; P6 (6,\n"
"3N) the rows of the basis's pseudo-inverse that give the translation and the rotation vector about\n"
"the entry; E (3, 3N) the entry's displacement per marker displacement; Q (3N, 3N) the part of a\n"
"marker displacement the model leaves. d = live - reference; (t, w) = P6 d; R = exp(w); the live\n"
"markers pulled back, m_i = R^T (live_i - entry - t) + entry - reference_i; out (4,) = the entry\n"
"R (E m) + entry + t, then the per-marker RMS of Q m (mm). Returns 0; -1 (out undefined) when a\n"
"value is not finite or N > 64: the numpy code decides. TypeError / ValueError for a bad buffer.");

static PyObject *k_pattern_entry(PyObject *self, PyObject *args)
{
    static const BufSpec spec[7] = {
        {"P6", 2, {6, -1}, 0}, {"E", 2, {3, -1}, 0}, {"Q", 2, {-1, -1}, 0}, {"reference", 2, {-1, 3}, 0},
        {"live", 2, {-1, 3}, 0}, {"entry", 1, {3}, 0}, {"out", 1, {4}, 1}};
    PyObject *o[7];
    double *q[7];
    if (!PyArg_ParseTuple(args, "OOOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6])) {
        return NULL;
    }
    Py_buffer views[7];
    PyObject *result = NULL;
    if (get_all(o, spec, 7, views, q) != 0) {
        goto done;
    }
    Py_ssize_t n = views[3].shape[0], m = 3 * n;
    if (views[4].shape[0] != n) {
        PyErr_Format(PyExc_ValueError, "pattern_entry: live has %zd rows, the reference %zd", views[4].shape[0],
                     n);
        goto done;
    }
    if (views[0].shape[1] != m || views[1].shape[1] != m || views[2].shape[0] != m || views[2].shape[1] != m) {
        PyErr_Format(PyExc_ValueError, "pattern_entry: P6, E and Q must have 3N = %zd columns (Q %zd rows)", m,
                     m);
        goto done;
    }
    if (n > TARGET_MAX_MARKERS || n < 1) {
        result = PyLong_FromLong(-1);
        goto done;
    }
    const double *P6 = q[0], *E = q[1], *Q = q[2], *ref = q[3], *live = q[4], *entry = q[5];
    double d[3 * TARGET_MAX_MARKERS], moved[3 * TARGET_MAX_MARKERS], p6[6] = {0.0}, R[9];
    for (Py_ssize_t k = 0; k < m; k++) {
        d[k] = live[k] - ref[k];
    }
    for (int r = 0; r < 6; r++) {
        for (Py_ssize_t k = 0; k < m; k++) {
            p6[r] += P6[r * m + k] * d[k];
        }
    }
    if (!all_finite(p6, 6) || rodrigues(p6 + 3, R) != 0) {
        result = PyLong_FromLong(-1);
        goto done;
    }
    for (Py_ssize_t i = 0; i < n; i++) {   /* R^T (live_i - entry - t) + entry - reference_i */
        double a[3], b[3];
        for (int j = 0; j < 3; j++) {
            a[j] = live[3 * i + j] - entry[j] - p6[j];
        }
        mat3t_vec(R, a, b);
        for (int j = 0; j < 3; j++) {
            moved[3 * i + j] = b[j] + entry[j] - ref[3 * i + j];
        }
    }
    double de[3] = {0.0, 0.0, 0.0}, ss = 0.0, rde[3];
    for (int j = 0; j < 3; j++) {
        for (Py_ssize_t k = 0; k < m; k++) {
            de[j] += E[j * m + k] * moved[k];
        }
    }
    for (Py_ssize_t r = 0; r < m; r++) {
        double u = 0.0;
        for (Py_ssize_t k = 0; k < m; k++) {
            u += Q[r * m + k] * moved[k];
        }
        ss += u * u;
    }
    mat3_vec(R, de, rde);
    double *out = q[6];
    for (int j = 0; j < 3; j++) {
        out[j] = rde[j] + entry[j] + p6[j];
    }
    out[3] = sqrt(ss / (double)n);
    result = PyLong_FromLong(all_finite(out, 4) ? 0 : -1);
done:
    release(views, 7);
    return result;
}

/* ---- module --------------------------------------------------------------------------------- */

static PyMethodDef native_methods[] = {
    {"horn", k_horn, METH_VARARGS, horn_doc},
    {"track", k_track, METH_VARARGS, track_doc},
    {"ur_newton", k_ur_newton, METH_VARARGS, ur_newton_doc},
    {"filter_feed", k_filter_feed, METH_VARARGS, filter_feed_doc},
    {"filter_pose", k_filter_pose, METH_VARARGS, filter_pose_doc},
    {"tcp_setpoint", k_tcp_setpoint, METH_VARARGS, tcp_setpoint_doc},
    {"ar_feed", k_ar_feed, METH_VARARGS, ar_feed_doc},
    {"ar_forecast", k_ar_forecast, METH_VARARGS, ar_forecast_doc},
    {"target_score", k_target_score, METH_VARARGS, target_score_doc},
    {"target_turn", k_target_turn, METH_VARARGS, target_turn_doc},
    {"turn_about", k_turn_about, METH_VARARGS, turn_about_doc},
    {"local_change", k_local_change, METH_VARARGS, local_change_doc},
    {"pattern_entry", k_pattern_entry, METH_VARARGS, pattern_entry_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef native_module = {
    PyModuleDef_HEAD_INIT, "_native",
    "The controller's per-pair marker geometry in compiled code (hil/geometry/_native.c).", -1,
    native_methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__native(void)
{
    return PyModule_Create(&native_module);
}
