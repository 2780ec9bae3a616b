/*
 * hil.vision._kernel: the per-ring arithmetic of hil/vision/ring_edges.py and
 * hil/vision/ellipse.py (fit_ellipse_arrays) in compiled code.
 *
 * Contract: only the Python C API and the buffer protocol. Every array is passed in C-contiguous
 * with the documented item type and shape, outputs are written into arrays the caller allocated;
 * every buffer is checked (format, item size, dimensions, contiguity, writability, consistent
 * lengths) and a bad one raises TypeError / ValueError naming the argument. No global mutable
 * state; the GIL is held throughout (the work per call is a few tens of microseconds).
 *
 * The arithmetic follows the numpy reference expression by expression (same operand order, no
 * reassociation, compiled without -ffast-math and without FP contraction), so that results agree
 * with it to rounding: only the order of a few sums differs (numpy's pairwise sums and BLAS
 * products) and libm's cos/sin/acos may differ from numpy's by an ulp. The references:
 *   ring_geometry / ray_maps / ring_edges: hil.vision.ring_edges.ring_edges_multi (numpy path);
 *   fit_ellipses: hil.vision.ellipse.fit_ellipse_arrays (numpy path): the direct ellipse-specific
 *   fit (Fitzgibbon, Pilu & Fisher 1999, eq 7) in the reduced form of Halir & Flusser 1998, the
 *   generalised eigenvector by the Viete root of the cubic (hil.vision.sym3.ellipse_eigvec), one
 *   robust re-fit without the points beyond 3 MAD of the Sampson distances;
 *   ideal_affines / conics_to_ideal: hil.vision.stereo._ideal_with_affines (OpenCV's undistortion
 *   fixed point, cvUndistortPointsInternal, for an identity camera) and _to_ideal_stack.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <float.h>
#include <math.h>
#include <string.h>

#define RAY_STEP 0.25
#define MAX_SAMPLES 1000000

/* ---- buffers ------------------------------------------------------------------------------ */

typedef struct {
    Py_buffer views[24];
    int count;
} BufSet;

static void bufs_release(BufSet *bs)
{
    for (int i = 0; i < bs->count; i++) {
        PyBuffer_Release(&bs->views[i]);
    }
    bs->count = 0;
}

/* kind: 'd' float64, 'f' float32, 'B' uint8, '?' bool, 'q' int64. shape[i] < 0: any length.
 * Returns the data pointer (NULL with an exception set). */
static void *get_buf(BufSet *bs, PyObject *obj, const char *name, char kind, int ndim,
                     const Py_ssize_t *shape, int writable, Py_ssize_t *shape_out)
{
    if (bs->count >= (int)(sizeof(bs->views) / sizeof(bs->views[0]))) {
        PyErr_SetString(PyExc_RuntimeError, "_kernel: too many buffers");
        return NULL;
    }
    Py_buffer *v = &bs->views[bs->count];
    if (PyObject_GetBuffer(obj, v, PyBUF_RECORDS_RO) != 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s: expected an array (buffer), got %.100s", name,
                     Py_TYPE(obj)->tp_name);
        return NULL;
    }
    bs->count++;
    const char *fmt = v->format ? v->format : "B";
    if (fmt[0] == '@' || fmt[0] == '=' || fmt[0] == '<') {
        fmt++;
    }
    int fmt_ok;
    Py_ssize_t want_size;
    switch (kind) {
    case 'd': fmt_ok = strcmp(fmt, "d") == 0; want_size = 8; break;
    case 'f': fmt_ok = strcmp(fmt, "f") == 0; want_size = 4; break;
    case 'B': fmt_ok = strcmp(fmt, "B") == 0; want_size = 1; break;
    case '?': fmt_ok = strcmp(fmt, "?") == 0; want_size = 1; break;
    default: fmt_ok = strcmp(fmt, "q") == 0 || strcmp(fmt, "l") == 0; want_size = 8; break;
    }
    static const char *names[] = {"float64", "float32", "uint8", "bool", "int64"};
    const char *tname = kind == 'd' ? names[0] : kind == 'f' ? names[1] : kind == 'B' ? names[2]
                        : kind == '?' ? names[3] : names[4];
    if (!fmt_ok || v->itemsize != want_size) {
        PyErr_Format(PyExc_TypeError, "%s: expected %s items, got format '%s' (item size %zd)", name,
                     tname, v->format ? v->format : "B", v->itemsize);
        return NULL;
    }
    if (v->ndim != ndim) {
        PyErr_Format(PyExc_ValueError, "%s: expected %d dimensions, got %d", name, ndim, v->ndim);
        return NULL;
    }
    for (int i = 0; i < ndim; i++) {
        if (shape[i] >= 0 && v->shape[i] != shape[i]) {
            PyErr_Format(PyExc_ValueError, "%s: dimension %d is %zd, expected %zd", name, i,
                         v->shape[i], shape[i]);
            return NULL;
        }
        if (shape_out) {
            shape_out[i] = v->shape[i];
        }
    }
    if (!PyBuffer_IsContiguous(v, 'C')) {
        PyErr_Format(PyExc_ValueError, "%s: must be C-contiguous", name);
        return NULL;
    }
    if (writable && v->readonly) {
        PyErr_Format(PyExc_ValueError, "%s: must be writable", name);
        return NULL;
    }
    return v->buf;
}

/* ---- ring geometry ------------------------------------------------------------------------ */

/* ring_edges.ellipse_radius of one direction */
static double ellipse_radius(double a, double b, double angle, double theta)
{
    double phi = theta - angle;
    double bc = b * cos(phi), as = a * sin(phi);
    return a * b / sqrt(bc * bc + as * as);
}

PyDoc_STRVAR(ring_geometry_doc,
"ring_geometry(outer, inner, theta, r_out, r_in, n_samples) -> int\n\n"
"Radii of the seeds' outer / inner ellipses along the rays (px) into r_out, r_in (E, n) and the\n"
"samples per ring ceil((max r_out + 3) / 0.25) into n_samples (E,) int64; returns their maximum\n"
"S (1 for E = 0). outer, inner: (E, 3) float64 (a, b, angle); theta: (n,) float64.\n"
"Raises ValueError when a radius is not finite or a ring needs more than 1e6 samples.");

static PyObject *k_ring_geometry(PyObject *self, PyObject *args)
{
    PyObject *o_outer, *o_inner, *o_theta, *o_rout, *o_rin, *o_ns;
    if (!PyArg_ParseTuple(args, "OOOOOO:ring_geometry", &o_outer, &o_inner, &o_theta, &o_rout,
                          &o_rin, &o_ns)) {
        return NULL;
    }
    BufSet bs = {.count = 0};
    PyObject *ret = NULL;
    Py_ssize_t sh[2] = {-1, 3}, got[2], n;
    const double *outer = get_buf(&bs, o_outer, "outer", 'd', 2, sh, 0, got);
    if (!outer) goto done;
    Py_ssize_t E = got[0];
    sh[0] = E;
    const double *inner = get_buf(&bs, o_inner, "inner", 'd', 2, sh, 0, NULL);
    if (!inner) goto done;
    Py_ssize_t sh1[1] = {-1};
    const double *theta = get_buf(&bs, o_theta, "theta", 'd', 1, sh1, 0, &n);
    if (!theta) goto done;
    Py_ssize_t sh2[2] = {E, n};
    double *rout = get_buf(&bs, o_rout, "r_out", 'd', 2, sh2, 1, NULL);
    if (!rout) goto done;
    double *rin = get_buf(&bs, o_rin, "r_in", 'd', 2, sh2, 1, NULL);
    if (!rin) goto done;
    Py_ssize_t she[1] = {E};
    long long *ns = get_buf(&bs, o_ns, "n_samples", 'q', 1, she, 1, NULL);
    if (!ns) goto done;
    if (n < 1) {
        PyErr_SetString(PyExc_ValueError, "theta: needs at least one ray");
        goto done;
    }
    long long S = 1;
    for (Py_ssize_t e = 0; e < E; e++) {
        double rmax = -INFINITY;
        for (Py_ssize_t k = 0; k < n; k++) {
            double ro = ellipse_radius(outer[3 * e], outer[3 * e + 1], outer[3 * e + 2], theta[k]);
            double ri = ellipse_radius(inner[3 * e], inner[3 * e + 1], inner[3 * e + 2], theta[k]);
            if (!isfinite(ro) || !isfinite(ri)) {
                PyErr_Format(PyExc_ValueError, "outer / inner: ring %zd has a radius that is not finite", e);
                goto done;
            }
            rout[e * n + k] = ro;
            rin[e * n + k] = ri;
            if (ro > rmax) rmax = ro;
        }
        double cnt = ceil((rmax + 3.0) / RAY_STEP);
        if (!(cnt >= 1.0 && cnt <= MAX_SAMPLES)) {
            PyErr_Format(PyExc_ValueError, "outer: ring %zd needs %g samples per ray (1 to %d)", e, cnt,
                         MAX_SAMPLES);
            goto done;
        }
        ns[e] = (long long)cnt;
        if (ns[e] > S) S = ns[e];
    }
    ret = PyLong_FromLongLong(S);
done:
    bufs_release(&bs);
    return ret;
}

PyDoc_STRVAR(ray_maps_doc,
"ray_maps(origin, cos_t, sin_t, mapx, mapy) -> None\n\n"
"The sample positions of every ray: mapx[e, k, j] = float32(ox + (j * 0.25) cos_t[k]) (px, image\n"
"coordinates), mapy likewise with sin_t. origin (E, 2), cos_t / sin_t (n,) float64; mapx, mapy\n"
"(E, n, S) float32, written.");

static PyObject *k_ray_maps(PyObject *self, PyObject *args)
{
    PyObject *o_origin, *o_cos, *o_sin, *o_mx, *o_my;
    if (!PyArg_ParseTuple(args, "OOOOO:ray_maps", &o_origin, &o_cos, &o_sin, &o_mx, &o_my)) {
        return NULL;
    }
    BufSet bs = {.count = 0};
    PyObject *ret = NULL;
    Py_ssize_t sh[3] = {-1, 2, -1}, got[3], n;
    const double *origin = get_buf(&bs, o_origin, "origin", 'd', 2, sh, 0, got);
    if (!origin) goto done;
    Py_ssize_t E = got[0];
    Py_ssize_t sh1[1] = {-1};
    const double *ct = get_buf(&bs, o_cos, "cos_t", 'd', 1, sh1, 0, &n);
    if (!ct) goto done;
    sh1[0] = n;
    const double *st = get_buf(&bs, o_sin, "sin_t", 'd', 1, sh1, 0, NULL);
    if (!st) goto done;
    sh[0] = E; sh[1] = n; sh[2] = -1;
    float *mx = get_buf(&bs, o_mx, "mapx", 'f', 3, sh, 1, got);
    if (!mx) goto done;
    Py_ssize_t S = got[2];
    sh[2] = S;
    float *my = get_buf(&bs, o_my, "mapy", 'f', 3, sh, 1, NULL);
    if (!my) goto done;
    for (Py_ssize_t e = 0; e < E; e++) {
        double ox = origin[2 * e], oy = origin[2 * e + 1];
        for (Py_ssize_t k = 0; k < n; k++) {
            float *px = mx + (e * n + k) * S, *py = my + (e * n + k) * S;
            for (Py_ssize_t j = 0; j < S; j++) {
                double r = (double)j * RAY_STEP;
                px[j] = (float)(ox + r * ct[k]);
                py[j] = (float)(oy + r * st[k]);
            }
        }
    }
    ret = Py_NewRef(Py_None);
done:
    bufs_release(&bs);
    return ret;
}

/* ---- ring edges --------------------------------------------------------------------------- */

/* The element of rank cnt // 2 of grey levels counted in hist[0..256] (256: +inf); +inf when
 * cnt is 0 (ring_edges._upper_median). */
static double hist_upper_median(const long long *hist, long long cnt)
{
    if (cnt == 0) return INFINITY;
    long long rank = cnt / 2, acc = 0;
    for (int g = 0; g < 256; g++) {
        acc += hist[g];
        if (acc > rank) return (double)g;
    }
    return INFINITY;
}

typedef struct {
    const unsigned char *grey;
    int dark;
    Py_ssize_t n, S, ns;
    const double *rout, *rin;
} RingIn;

static inline double level(const RingIn *R, Py_ssize_t k, Py_ssize_t j)
{
    unsigned char g = R->grey[k * R->S + j];
    return R->dark ? (double)g : (double)(255 - g);
}

/* The ring, background and hole levels of one ring and each ray's ring minimum jmin. */
static void ring_levels(const RingIn *R, Py_ssize_t *jmin, double *ring, double *bg, double *hole)
{
    long long hist[257], cnt = 0;
    Py_ssize_t n = R->n, S = R->S, ns = R->ns;
    memset(hist, 0, sizeof(hist));
    double rin_min = INFINITY;
    long long tail_cnt = 0, tail_hist[256], last_sum = 0;
    memset(tail_hist, 0, sizeof(tail_hist));
    for (Py_ssize_t k = 0; k < n; k++) {
        double ro = R->rout[k], ri = R->rin[k];
        double lo = ceil((ri - 0.5) / RAY_STEP - 1e-9), hi = floor((ro + 0.5) / RAY_STEP + 1e-9);
        double best = INFINITY;
        Py_ssize_t jb = 0;
        for (Py_ssize_t j = 0; j < S; j++) {
            if ((double)j >= lo && (double)j <= hi && j < ns) {
                double v = level(R, k, j);
                if (v < best) { best = v; jb = j; }
            }
        }
        jmin[k] = jb;
        hist[isinf(best) ? 256 : (int)best]++;
        cnt++;
        double jt = ceil((ro + 1.8) / RAY_STEP - 1e-9);
        for (Py_ssize_t j = 0; j < ns; j++) {
            if ((double)j >= jt) { tail_hist[(int)level(R, k, j)]++; tail_cnt++; }
        }
        last_sum += (long long)level(R, k, ns - 1);
        if (ri < rin_min || isnan(ri)) rin_min = ri;
    }
    /* the sorted minima's element n // 2 (inf sorts last) */
    long long acc = 0;
    *ring = INFINITY;
    for (int g = 0; g < 257; g++) {
        acc += hist[g];
        if (acc > cnt / 2) { *ring = g == 256 ? INFINITY : (double)g; break; }
    }
    if (tail_cnt > 0) {
        *bg = hist_upper_median(tail_hist, tail_cnt);
    } else {  /* float32 mean of the rays' last samples, as numpy's mean of a float32 array */
        *bg = (double)((float)last_sum / (float)n);
    }
    double h = 0.35 * rin_min;
    double hole_r = (h >= 0.3 || isnan(h)) ? h : 0.3;
    double nh = floor(hole_r / RAY_STEP + 1e-9) + 1.0;
    long long hh[256], hc = 0;
    memset(hh, 0, sizeof(hh));
    for (Py_ssize_t k = 0; k < n; k++) {
        for (Py_ssize_t j = 0; j < ns && (double)j < nh; j++) {
            hh[(int)level(R, k, j)]++;
            hc++;
        }
    }
    *hole = hist_upper_median(hh, hc);
}

/* ring_edges._crossings of one ray: the outer and inner edge radii and whether found. */
static void ray_crossings(const RingIn *R, Py_ssize_t k, Py_ssize_t jmin, double t_out, double t_in,
                          double *ro, int *ok_o, double *ri, int *ok_i)
{
    Py_ssize_t S = R->S, ns = R->ns, jo = 0, ji = S - 1;
    int found = 0;
    for (Py_ssize_t j = jmin + 1; j < ns; j++) {
        if (level(R, k, j) >= t_out) { jo = j; found = 1; break; }
    }
    *ok_o = found && jo > 0;
    Py_ssize_t jo1 = jo > 0 ? jo - 1 : 0;
    double p1 = level(R, k, jo), p0 = level(R, k, jo1);
    double den = p1 - p0 == 0 ? 1e-9 : p1 - p0;
    *ro = (double)jo1 * RAY_STEP + RAY_STEP * (t_out - p0) / den;
    found = 0;
    for (Py_ssize_t j = (jmin < S ? jmin : S) - 1; j >= 0; j--) {
        if (level(R, k, j) >= t_in) { ji = j; found = 1; break; }
    }
    *ok_i = found && ji < S - 1;
    double q0 = level(R, k, ji), q1 = level(R, k, ji + 1 < S ? ji + 1 : S - 1);
    den = q0 - q1 == 0 ? 1e-9 : q0 - q1;
    *ri = (double)ji * RAY_STEP + RAY_STEP * (q0 - t_in) / den;
}

typedef struct {
    double *xo, *yo, *xi, *yi, *frac;
    unsigned char *mo, *mi, *ok;
} EdgeOut;

static void one_ring(const RingIn *R, double ox, double oy, const double *ct, const double *st,
                     double min_contrast, double min_valid_fraction, Py_ssize_t *jmin, Py_ssize_t e,
                     EdgeOut *out)
{
    Py_ssize_t n = R->n;
    double ring, bg, hole;
    ring_levels(R, jmin, &ring, &bg, &hole);
    int contrast_ok = (bg - ring >= min_contrast) && (hole - ring >= 0.35 * min_contrast);
    double t_out = 0.5 * (bg + ring), t_in = 0.5 * (hole + ring);
    long long both = 0;
    for (Py_ssize_t k = 0; k < n; k++) {
        double ro, ri;
        int oko, oki;
        ray_crossings(R, k, jmin[k], t_out, t_in, &ro, &oko, &ri, &oki);
        double rout = R->rout[k], rin = R->rin[k];
        oko = oko && fabs(ro - rout) < 1.5 + 0.15 * rout;
        oki = oki && fabs(ri - rin) < 1.5 + 0.25 * rin;
        Py_ssize_t i = e * n + k;
        out->xo[i] = ox + ro * ct[k];
        out->yo[i] = oy + ro * st[k];
        out->xi[i] = ox + ri * ct[k];
        out->yi[i] = oy + ri * st[k];
        out->mo[i] = (unsigned char)oko;
        out->mi[i] = (unsigned char)oki;
        both += oko && oki;
    }
    out->frac[e] = (double)both / (double)n;
    out->ok[e] = (unsigned char)(contrast_ok && out->frac[e] >= min_valid_fraction);
}

PyDoc_STRVAR(ring_edges_doc,
"ring_edges(grey, dark_on_light, origin, cos_t, sin_t, r_out, r_in, n_samples, min_contrast,\n"
"           min_valid_fraction, xo, yo, mo, xi, yi, mi, frac, ok) -> None\n\n"
"The edge step of hil.vision.ring_edges.ring_edges_multi on sampled rays: grey (E, n, S) uint8\n"
"(the bicubic samples, radius j * 0.25 px), dark_on_light (E,) bool, origin (E, 2), cos_t /\n"
"sin_t (n,), r_out / r_in (E, n) float64 (ring_geometry), n_samples (E,) int64 (each <= S).\n"
"Writes the edge points xo, yo, xi, yi (E, n) float64 (px), masks mo, mi (E, n) bool, frac (E,)\n"
"float64 and ok (E,) bool.");

static PyObject *k_ring_edges(PyObject *self, PyObject *args)
{
    PyObject *o[18];
    double min_contrast, mvf;
    if (!PyArg_ParseTuple(args, "OOOOOOOOddOOOOOOOO:ring_edges", &o[0], &o[1], &o[2], &o[3], &o[4],
                          &o[5], &o[6], &o[7], &min_contrast, &mvf, &o[8], &o[9], &o[10], &o[11],
                          &o[12], &o[13], &o[14], &o[15])) {
        return NULL;
    }
    BufSet bs = {.count = 0};
    PyObject *ret = NULL;
    Py_ssize_t *jmin = NULL;
    Py_ssize_t sh[3] = {-1, -1, -1}, got[3];
    const unsigned char *grey = get_buf(&bs, o[0], "grey", 'B', 3, sh, 0, got);
    if (!grey) goto done;
    Py_ssize_t E = got[0], n = got[1], S = got[2];
    Py_ssize_t shE[1] = {E}, shE2[2] = {E, 2}, shn[1] = {n}, shEn[2] = {E, n};
    const unsigned char *dol = get_buf(&bs, o[1], "dark_on_light", '?', 1, shE, 0, NULL);
    const double *origin = dol ? get_buf(&bs, o[2], "origin", 'd', 2, shE2, 0, NULL) : NULL;
    const double *ct = origin ? get_buf(&bs, o[3], "cos_t", 'd', 1, shn, 0, NULL) : NULL;
    const double *st = ct ? get_buf(&bs, o[4], "sin_t", 'd', 1, shn, 0, NULL) : NULL;
    const double *rout = st ? get_buf(&bs, o[5], "r_out", 'd', 2, shEn, 0, NULL) : NULL;
    const double *rin = rout ? get_buf(&bs, o[6], "r_in", 'd', 2, shEn, 0, NULL) : NULL;
    const long long *ns = rin ? get_buf(&bs, o[7], "n_samples", 'q', 1, shE, 0, NULL) : NULL;
    if (!ns) goto done;
    EdgeOut out;
    static const char *onames[] = {"xo", "yo", "mo", "xi", "yi", "mi"};
    void **optr[] = {(void **)&out.xo, (void **)&out.yo, (void **)&out.mo,
                     (void **)&out.xi, (void **)&out.yi, (void **)&out.mi};
    for (int i = 0; i < 6; i++) {
        char kind = (i == 2 || i == 5) ? '?' : 'd';
        *optr[i] = get_buf(&bs, o[8 + i], onames[i], kind, 2, shEn, 1, NULL);
        if (!*optr[i]) goto done;
    }
    out.frac = get_buf(&bs, o[14], "frac", 'd', 1, shE, 1, NULL);
    if (!out.frac) goto done;
    out.ok = get_buf(&bs, o[15], "ok", '?', 1, shE, 1, NULL);
    if (!out.ok) goto done;
    if (n < 1 && E > 0) {
        PyErr_SetString(PyExc_ValueError, "grey: needs at least one ray");
        goto done;
    }
    for (Py_ssize_t e = 0; e < E; e++) {
        if (ns[e] < 1 || ns[e] > S) {
            PyErr_Format(PyExc_ValueError, "n_samples: ring %zd has %lld, expected 1 to %zd", e, ns[e], S);
            goto done;
        }
    }
    jmin = PyMem_Malloc(sizeof(Py_ssize_t) * (size_t)(n > 0 ? n : 1));
    if (!jmin) { PyErr_NoMemory(); goto done; }
    for (Py_ssize_t e = 0; e < E; e++) {
        RingIn R = {grey + e * n * S, dol[e] != 0, n, S, (Py_ssize_t)ns[e], rout + e * n, rin + e * n};
        one_ring(&R, origin[2 * e], origin[2 * e + 1], ct, st, min_contrast, mvf, jmin, e, &out);
    }
    ret = Py_NewRef(Py_None);
done:
    PyMem_Free(jmin);
    bufs_release(&bs);
    return ret;
}

/* ---- ellipse fits ------------------------------------------------------------------------- */

/* sym3.ellipse_eigvec of one matrix (upper triangle s00 s01 s02 s11 s12 s22): a (3,), ok. */
static int ellipse_eigvec(const double *s, double *a)
{
    double s00 = s[0], s01 = s[1], s02 = s[2], s11 = s[3], s12 = s[4], s22 = s[5];
    double det = s00 * (s11 * s22 - s12 * s12) - s01 * (s01 * s22 - s12 * s02) + s02 * (s01 * s12 - s11 * s02);
    int pd = (s00 > 0) && (s00 * s11 - s01 * s01 > 0) && (det > 0);
    double c2 = s11 - s02;
    double c1 = -0.25 * (s00 * s22 - 4.0 * s01 * s12 + 4.0 * s11 * s02 - s02 * s02);
    double c0 = -0.25 * det;
    double sh = c2 / 3.0;
    double p = c1 / 3.0 - sh * sh;
    double q = sh * sh * sh - 0.5 * c1 * sh + 0.5 * c0;
    double mp = -p;
    if (!(mp >= 0.0) && !isnan(mp)) mp = 0.0;  /* np.maximum(-p, 0.0) */
    double m = sqrt(mp);
    double m3 = m * m * m;
    double cos3 = m3 > 0 ? -q / m3 : 0.0;
    if (cos3 < -1.0) cos3 = -1.0;
    else if (cos3 > 1.0) cos3 = 1.0;
    double lam = 2.0 * m * cos(acos(cos3) / 3.0) - sh;
    for (int it = 0; it < 2; it++) {
        double f = ((lam + c2) * lam + c1) * lam + c0;
        double df = (3.0 * lam + 2.0 * c2) * lam + c1;
        lam = lam - (df != 0 ? f / df : 0.0);
    }
    double m02 = s02 - 2.0 * lam, m11 = s11 + lam;
    double adj[3][3] = {
        {m11 * s22 - s12 * s12, m02 * s12 - s01 * s22, s01 * s12 - m02 * m11},
        {m02 * s12 - s01 * s22, s00 * s22 - m02 * m02, s01 * m02 - s00 * s12},
        {s01 * s12 - m02 * m11, s01 * m02 - s00 * s12, s00 * m11 - s01 * s01},
    };
    int kb = 0;  /* np.argmax of |diagonal|: the first maximum, a NaN wins */
    double best = fabs(adj[0][0]);
    if (!isnan(best)) {
        for (int k = 1; k < 3; k++) {
            double v = fabs(adj[k][k]);
            if (isnan(v)) { kb = k; break; }
            if (v > best) { best = v; kb = k; }
        }
    }
    for (int i = 0; i < 3; i++) a[i] = adj[i][kb];
    return pd && lam > 0 && (a[0] != 0 || a[1] != 0 || a[2] != 0);
}

/* ellipse._direct_fit_batch of one point set (weights w: 0 or 1): the normalised conic C (3x3,
 * row-major); returns ok. */
static int direct_fit(const double *x, const double *y, const unsigned char *w, Py_ssize_t R, double *C)
{
    double n = 0, sx = 0, sy = 0;
    for (Py_ssize_t i = 0; i < R; i++) n += w[i] ? 1.0 : 0.0;
    int ok = n >= 6;
    if (!ok) n = 1.0;
    for (Py_ssize_t i = 0; i < R; i++) {
        if (w[i]) { sx += x[i]; sy += y[i]; }
    }
    double mx = sx / n, my = sy / n, ss = 0;
    for (Py_ssize_t i = 0; i < R; i++) {
        double xc = x[i] - mx, yc = y[i] - my;
        if (w[i]) ss += xc * xc + yc * yc;
    }
    double s = sqrt(ss / (2.0 * n));
    if (!(s > 0)) s = 1.0;
    double S[6][6];
    memset(S, 0, sizeof(S));
    for (Py_ssize_t i = 0; i < R; i++) {
        if (!w[i]) continue;
        double xn = (x[i] - mx) / s, yn = (y[i] - my) / s;
        double D[6] = {xn * xn, xn * yn, yn * yn, xn, yn, 1.0};
        for (int r = 0; r < 6; r++)
            for (int c = r; c < 6; c++) S[r][c] += D[r] * D[c];
    }
    for (int r = 0; r < 6; r++)
        for (int c = 0; c < r; c++) S[r][c] = S[c][r];
    /* S3 = S[3:, 3:]: det and adjugate (sym3.det_sym3, adj_sym3) */
    double a = S[3][3], b = S[3][4], c = S[3][5], d = S[4][4], e = S[4][5], f = S[5][5];
    double det3 = a * (d * f - e * e) - b * (b * f - c * e) + c * (b * e - c * d);
    ok = ok && fabs(det3) > 1e-12;
    double A[3][3] = {{d * f - e * e, c * e - b * f, b * e - c * d},
                      {c * e - b * f, a * f - c * c, b * c - a * e},
                      {b * e - c * d, b * c - a * e, a * d - b * b}};
    double scale = -1.0 / (ok ? det3 : 1.0);
    double T[3][3], Sr[3][3];
    for (int i = 0; i < 3; i++)  /* T = adj(S3) S2^T (-1 / det S3) (Halir & Flusser) */
        for (int j = 0; j < 3; j++)
            T[i][j] = (A[i][0] * S[j][3] + A[i][1] * S[j][4] + A[i][2] * S[j][5]) * scale;
    for (int i = 0; i < 3; i++)  /* the reduced scatter matrix S1 + S2 T */
        for (int j = 0; j < 3; j++)
            Sr[i][j] = S[i][j] + (S[i][3] * T[0][j] + S[i][4] * T[1][j] + S[i][5] * T[2][j]);
    double su[6];
    int idx[6][2] = {{0, 0}, {0, 1}, {0, 2}, {1, 1}, {1, 2}, {2, 2}};
    for (int q = 0; q < 6; q++) {
        int i = idx[q][0], j = idx[q][1];
        double v = 0.5 * (Sr[i][j] + Sr[j][i]);
        su[q] = isfinite(v) ? v : 0.0;
    }
    double tr = su[0] + su[3] + su[5];
    int pos = ok && tr > 0;
    if (pos) {
        su[0] += 1e-12 * tr; su[3] += 1e-12 * tr; su[5] += 1e-12 * tr;
    } else {
        su[0] = 1.0; su[1] = 0.0; su[2] = 0.0; su[3] = 1.0; su[4] = 0.0; su[5] = 1.0;
    }
    double a1[3], a2[3];
    int good = ellipse_eigvec(su, a1);
    ok = ok && pos && good && (4.0 * a1[0] * a1[2] - a1[1] * a1[1] > 0);
    for (int i = 0; i < 3; i++) a2[i] = T[i][0] * a1[0] + T[i][1] * a1[1] + T[i][2] * a1[2];
    double Cn[3][3] = {{a1[0], 0.5 * a1[1], 0.5 * a2[0]},
                       {0.5 * a1[1], a1[2], 0.5 * a2[1]},
                       {0.5 * a2[0], 0.5 * a2[1], a2[2]}};
    double N[3][3] = {{1.0 / s, 0.0, -mx / s}, {0.0, 1.0 / s, -my / s}, {0.0, 0.0, 1.0}};
    double NtC[3][3], nrm = 0;
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            NtC[i][j] = N[0][i] * Cn[0][j] + N[1][i] * Cn[1][j] + N[2][i] * Cn[2][j];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double v = NtC[i][0] * N[0][j] + NtC[i][1] * N[1][j] + NtC[i][2] * N[2][j];
            C[3 * i + j] = v;
            nrm += v * v;
        }
    nrm = sqrt(nrm);
    for (int i = 0; i < 9; i++) C[i] /= nrm;
    return ok;
}

/* ellipse._sampson_batch of one point: the (signed) first-order distance to conic C. */
static inline double sampson(const double *C, double x, double y)
{
    double gx = C[0] * x + C[1] * y + C[2];
    double gy = C[3] * x + C[4] * y + C[5];
    double g2 = C[6] * x + C[7] * y + C[8];
    double alg = x * gx + y * gy + g2;
    double grad = 2.0 * sqrt(gx * gx + gy * gy);
    return alg / (grad > 1e-300 || isnan(grad) ? grad : 1e-300);
}

static int cmp_nan_last(const void *pa, const void *pb)
{
    double a = *(const double *)pa, b = *(const double *)pb;
    if (isnan(a)) return isnan(b) ? 0 : 1;
    if (isnan(b)) return -1;
    return (a > b) - (a < b);
}

typedef struct {
    double *conic, *center, *a, *b, *angle, *res;
    long long *npts;
    unsigned char *good, *used;
} FitOut;

/* fit_ellipse_arrays of row e: fit, drop beyond 3 MAD, re-fit, ellipse parameters. */
static void robust_fit(const double *x, const double *y, const unsigned char *m, Py_ssize_t R,
                       double *d, double *srt, Py_ssize_t e, FitOut *out)
{
    double *C = out->conic + 9 * e;
    unsigned char *used = out->used + R * e;
    int ok = direct_fit(x, y, m, R, C);
    Py_ssize_t cnt = 0, n_keep = 0;
    for (Py_ssize_t i = 0; i < R; i++) {
        d[i] = fabs(sampson(C, x[i], y[i]));
        if (m[i]) srt[cnt++] = d[i];
        used[i] = m[i] ? 1 : 0;
    }
    qsort(srt, (size_t)cnt, sizeof(double), cmp_nan_last);
    double mad = (cnt > 0 ? srt[cnt / 2] : INFINITY) * 1.4826 + 1e-3;
    double thr = 3.0 * mad;
    if (!(thr >= 0.05) && !isnan(thr)) thr = 0.05;
    for (Py_ssize_t i = 0; i < R; i++) n_keep += m[i] && d[i] <= thr;
    if (n_keep < cnt && n_keep >= 6) {
        for (Py_ssize_t i = 0; i < R; i++) used[i] = m[i] && d[i] <= thr;
        ok = direct_fit(x, y, used, R, C) && ok;
        for (Py_ssize_t i = 0; i < R; i++) d[i] = fabs(sampson(C, x[i], y[i]));
    }
    if (C[0] + C[4] < 0)
        for (int i = 0; i < 9; i++) C[i] = -C[i];
    double A = C[0], B = C[1], Cq = C[4], dd = C[2], ee = C[5], ff = C[8];
    double det = A * Cq - B * B;
    double cx = (B * ee - Cq * dd) / det, cy = (B * dd - A * ee) / det;
    double k = ff + dd * cx + ee * cy;
    double mean = 0.5 * (A + Cq), diff = hypot(0.5 * (A - Cq), B);
    double lam_s = mean - diff, lam_b = mean + diff;
    double a_ax = sqrt(-k / lam_s), b_ax = sqrt(-k / lam_b);
    out->angle[e] = 0.5 * atan2(2.0 * B, A - Cq) + M_PI / 2;
    out->good[e] = (unsigned char)(ok && det > 0 && k < 0 && lam_s > 0 && isfinite(a_ax) && isfinite(b_ax));
    long long np_ = 0;
    double sq = 0;
    for (Py_ssize_t i = 0; i < R; i++) {
        if (used[i]) { np_++; sq += d[i] * d[i]; }
    }
    out->res[e] = sqrt(sq / (double)(np_ > 1 ? np_ : 1));
    out->npts[e] = np_;
    out->a[e] = a_ax;
    out->b[e] = b_ax;
    out->center[2 * e] = cx;
    out->center[2 * e + 1] = cy;
}

PyDoc_STRVAR(fit_ellipses_doc,
"fit_ellipses(X, Y, M, conic, center, a, b, angle, residual, n_points, good, used) -> None\n\n"
"hil.vision.ellipse.fit_ellipse_arrays: robust direct ellipse fits of E point sets X, Y (E, R)\n"
"float64 (px), M (E, R) bool the points to use. Writes conic (E, 3, 3), center (E, 2), a, b,\n"
"angle, residual (E,) float64, n_points (E,) int64, good (E,) bool and used (E, R) bool (the\n"
"points of the final fit).");

static PyObject *k_fit_ellipses(PyObject *self, PyObject *args)
{
    PyObject *o[12];
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOO:fit_ellipses", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6], &o[7], &o[8], &o[9], &o[10], &o[11])) {
        return NULL;
    }
    BufSet bs = {.count = 0};
    PyObject *ret = NULL;
    double *d = NULL;
    Py_ssize_t sh[2] = {-1, -1}, got[2];
    const double *X = get_buf(&bs, o[0], "X", 'd', 2, sh, 0, got);
    if (!X) goto done;
    Py_ssize_t E = got[0], R = got[1];
    Py_ssize_t shER[2] = {E, R}, shE[1] = {E}, shE2[2] = {E, 2}, shE33[3] = {E, 3, 3};
    const double *Y = get_buf(&bs, o[1], "Y", 'd', 2, shER, 0, NULL);
    const unsigned char *M = Y ? get_buf(&bs, o[2], "M", '?', 2, shER, 0, NULL) : NULL;
    if (!M) goto done;
    FitOut out;
    out.conic = get_buf(&bs, o[3], "conic", 'd', 3, shE33, 1, NULL);
    out.center = out.conic ? get_buf(&bs, o[4], "center", 'd', 2, shE2, 1, NULL) : NULL;
    if (!out.center) goto done;
    static const char *names[] = {"a", "b", "angle", "residual"};
    double **fptr[] = {&out.a, &out.b, &out.angle, &out.res};
    for (int i = 0; i < 4; i++) {
        *fptr[i] = get_buf(&bs, o[5 + i], names[i], 'd', 1, shE, 1, NULL);
        if (!*fptr[i]) goto done;
    }
    out.npts = get_buf(&bs, o[9], "n_points", 'q', 1, shE, 1, NULL);
    out.good = out.npts ? get_buf(&bs, o[10], "good", '?', 1, shE, 1, NULL) : NULL;
    out.used = out.good ? get_buf(&bs, o[11], "used", '?', 2, shER, 1, NULL) : NULL;
    if (!out.used) goto done;
    d = PyMem_Malloc(sizeof(double) * (size_t)(2 * R + 1));
    if (!d) { PyErr_NoMemory(); goto done; }
    for (Py_ssize_t e = 0; e < E; e++) {
        robust_fit(X + e * R, Y + e * R, M + e * R, R, d, d + R, e, &out);
    }
    ret = Py_NewRef(Py_None);
done:
    PyMem_Free(d);
    bufs_release(&bs);
    return ret;
}

/* ---- ring check ---------------------------------------------------------------------------- */

PyDoc_STRVAR(ring_check_doc,
"ring_check(a, b, center, residual, n_points, good, max_residual, concentric_tol, ratio,\n"
"           ratio_tol, eccentricity_tol, ok, ring_center, sigma, resid) -> None\n\n"
"The ring check and centre estimate of hil.vision.detect.fit_rings for m rings whose outer\n"
"ellipses are rows 0..m-1 and inner ellipses rows m..2m-1 of the fit outputs a, b, residual\n"
"(2m,) float64, center (2m, 2), n_points (2m,) int64, good (2m,) bool. Writes ok (m,) bool, the\n"
"edge-length-weighted centre ring_center (m, 2) px, its sigma (m,) px and the RMS residual over\n"
"both edges resid (m,) px.");

static PyObject *k_ring_check(PyObject *self, PyObject *args)
{
    PyObject *o[10];
    double max_res, ctol, ior, rtol, etol;
    if (!PyArg_ParseTuple(args, "OOOOOOdddddOOOO:ring_check", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &max_res, &ctol, &ior, &rtol, &etol, &o[6], &o[7], &o[8], &o[9])) {
        return NULL;
    }
    BufSet bs = {.count = 0};
    PyObject *ret = NULL;
    Py_ssize_t sh[1] = {-1}, got[1];
    const double *a = get_buf(&bs, o[0], "a", 'd', 1, sh, 0, got);
    if (!a) goto done;
    Py_ssize_t m2 = got[0], m = m2 / 2;
    if (m2 % 2) {
        PyErr_SetString(PyExc_ValueError, "a: expected an even length (outer then inner rows)");
        goto done;
    }
    Py_ssize_t sh2[1] = {m2}, shc[2] = {m2, 2}, shm[1] = {m}, shm2[2] = {m, 2};
    const double *b = get_buf(&bs, o[1], "b", 'd', 1, sh2, 0, NULL);
    const double *c = b ? get_buf(&bs, o[2], "center", 'd', 2, shc, 0, NULL) : NULL;
    const double *r = c ? get_buf(&bs, o[3], "residual", 'd', 1, sh2, 0, NULL) : NULL;
    const long long *np_ = r ? get_buf(&bs, o[4], "n_points", 'q', 1, sh2, 0, NULL) : NULL;
    const unsigned char *good = np_ ? get_buf(&bs, o[5], "good", '?', 1, sh2, 0, NULL) : NULL;
    unsigned char *ok = good ? get_buf(&bs, o[6], "ok", '?', 1, shm, 1, NULL) : NULL;
    double *rc = ok ? get_buf(&bs, o[7], "ring_center", 'd', 2, shm2, 1, NULL) : NULL;
    double *sigma = rc ? get_buf(&bs, o[8], "sigma", 'd', 1, shm, 1, NULL) : NULL;
    double *resid = sigma ? get_buf(&bs, o[9], "resid", 'd', 1, shm, 1, NULL) : NULL;
    if (!resid) goto done;
    for (Py_ssize_t k = 0; k < m; k++) {
        Py_ssize_t i = m + k;
        double ao = a[k], bo = b[k], ai = a[i], bi = b[i], ro = r[k], ri = r[i];
        double ratio = sqrt(ai * bi / (ao * bo));
        double ecc = fabs(bo / ao - bi / ai);
        double sep = hypot(c[2 * k] - c[2 * i], c[2 * k + 1] - c[2 * i + 1]);
        ok[k] = (unsigned char)(good[k] && good[i] && ro <= max_res && ri <= max_res
                                && sep <= ctol * ao + 0.15 && fabs(ratio - ior) <= rtol && ecc <= etol);
        double po = ao + bo, pi = ai + bi;
        double wo = po / (po + pi), wi = pi / (po + pi);
        rc[2 * k] = wo * c[2 * k] + wi * c[2 * i];
        rc[2 * k + 1] = wo * c[2 * k + 1] + wi * c[2 * i + 1];
        double no = (double)np_[k], ni = (double)np_[i];
        double mo = ro >= 0.01 || isnan(ro) ? ro : 0.01, mi = ri >= 0.01 || isnan(ri) ? ri : 0.01;
        double var_o = 2.0 * (mo * mo) / (no >= 1 ? no : 1.0);
        double var_i = 2.0 * (mi * mi) / (ni >= 1 ? ni : 1.0);
        sigma[k] = sqrt(wo * wo * var_o + wi * wi * var_i);
        double nn = (double)(np_[k] + np_[i]);
        resid[k] = sqrt((ro * ro * no + ri * ri * ni) / (nn >= 1 ? nn : 1.0));
    }
    ret = Py_NewRef(Py_None);
done:
    bufs_release(&bs);
    return ret;
}

/* ---- stereo: plane-normal perspective correction ----------------------------------------- */

/* Eigen-decomposition of a symmetric 3x3 matrix by cyclic Jacobi rotations (Golub & Van Loan,
 * 8.5): eigenvalues w ascending, eigenvectors the columns of V (unit, sign arbitrary). */
static void eigh3(const double *A_in, double *w, double V[3][3])
{
    double A[3][3];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            A[i][j] = A_in[3 * i + j];
            V[i][j] = i == j ? 1.0 : 0.0;
        }
    static const int pq[3][2] = {{0, 1}, {0, 2}, {1, 2}};
    for (int sweep = 0; sweep < 60; sweep++) {
        double off = fabs(A[0][1]) + fabs(A[0][2]) + fabs(A[1][2]);
        if (off == 0.0) break;
        for (int r = 0; r < 3; r++) {
            int p = pq[r][0], q = pq[r][1];
            double apq = A[p][q];
            if (apq == 0.0) continue;
            double g = 100.0 * fabs(apq);
            if (sweep > 3 && fabs(A[p][p]) + g == fabs(A[p][p]) && fabs(A[q][q]) + g == fabs(A[q][q])) {
                A[p][q] = A[q][p] = 0.0;
                continue;
            }
            double theta = (A[q][q] - A[p][p]) / (2.0 * apq);
            double t = 1.0 / (fabs(theta) + sqrt(theta * theta + 1.0));
            if (theta < 0) t = -t;
            if (!isfinite(theta)) t = 0.5 / theta;
            double c = 1.0 / sqrt(t * t + 1.0), s = t * c;
            for (int k = 0; k < 3; k++) {  /* A <- J^T A J, V <- V J */
                double akp = A[k][p], akq = A[k][q];
                A[k][p] = c * akp - s * akq;
                A[k][q] = s * akp + c * akq;
            }
            for (int k = 0; k < 3; k++) {
                double apk = A[p][k], aqk = A[q][k];
                A[p][k] = c * apk - s * aqk;
                A[q][k] = s * apk + c * aqk;
            }
            A[p][q] = A[q][p] = 0.0;
            for (int k = 0; k < 3; k++) {
                double vkp = V[k][p], vkq = V[k][q];
                V[k][p] = c * vkp - s * vkq;
                V[k][q] = s * vkp + c * vkq;
            }
        }
    }
    int ord[3] = {0, 1, 2};
    double d[3] = {A[0][0], A[1][1], A[2][2]};
    for (int i = 0; i < 3; i++)
        for (int j = i + 1; j < 3; j++)
            if (d[ord[j]] < d[ord[i]]) { int t = ord[i]; ord[i] = ord[j]; ord[j] = t; }
    double W[3][3];
    for (int j = 0; j < 3; j++) {
        w[j] = d[ord[j]];
        for (int i = 0; i < 3; i++) W[i][j] = V[i][ord[j]];
    }
    memcpy(V, W, sizeof(W));
}

/* ellipse.circle_normals_from_cones of one cone Q = K^T C K (Shiu & Ahmad 1989): the two
 * candidate unit normals towards the camera; returns ok. */
static int cone_normals(const double *Q, double *n1, double *n2)
{
    double lam[3], V[3][3];
    eigh3(Q, lam, V);
    int flip = (lam[0] > 0) + (lam[1] > 0) + (lam[2] > 0) == 1;
    double l1 = flip ? -lam[0] : lam[2], l2 = flip ? -lam[1] : lam[1], l3 = flip ? -lam[2] : lam[0];
    int c1 = flip ? 0 : 2, c3 = flip ? 2 : 0;
    int ok = l1 >= l2 && l2 > 0 && l3 < 0;
    double den = ok ? l1 - l3 : 1.0;
    double gg = (l1 - l2) / den, hh = (l2 - l3) / den;
    double g = sqrt(gg > 0.0 || isnan(gg) ? gg : 0.0), h = sqrt(hh > 0.0 || isnan(hh) ? hh : 0.0);
    double *out[2] = {n1, n2};
    for (int m = 0; m < 2; m++) {
        double sg = m == 0 ? 1.0 : -1.0, nn = 0;
        for (int i = 0; i < 3; i++) {
            out[m][i] = V[i][c3] * h + sg * (V[i][c1] * g);
            nn += out[m][i] * out[m][i];
        }
        nn = sqrt(nn);
        double flip_sign = out[m][2] / nn > 0 ? -1.0 : 1.0;
        for (int i = 0; i < 3; i++) out[m][i] = flip_sign * (out[m][i] / nn);
    }
    return ok;
}

/* K^T C K of a 3x3 conic (row-major) and an upper-triangular K */
static void cone_of(const double *C, const double *K, double *Q)
{
    double T[9];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            T[3 * i + j] = K[i] * C[j] + K[3 + i] * C[3 + j] + K[6 + i] * C[6 + j];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            Q[3 * i + j] = T[3 * i] * K[j] + T[3 * i + 1] * K[3 + j] + T[3 * i + 2] * K[6 + j];
}

/* pole of line l w.r.t. conic C minus the conic's centre (ellipse.poles_of_lines,
 * conics.conic_centers) */
static void pole_shift(const double *C, const double *l, double *out)
{
    double a = C[0], b = C[1], d = C[2], c = C[4], e = C[5], f = C[8];
    double A00 = c * f - e * e, A01 = d * e - b * f, A02 = b * e - c * d;
    double A11 = a * f - d * d, A12 = b * d - a * e, A22 = a * c - b * b;
    double p0 = A00 * l[0] + A01 * l[1] + A02 * l[2];
    double p1 = A01 * l[0] + A11 * l[1] + A12 * l[2];
    double p2 = A02 * l[0] + A12 * l[1] + A22 * l[2];
    double det = a * c - b * b;
    out[0] = p0 / p2 - (b * e - c * d) / det;
    out[1] = p1 / p2 - (b * d - a * e) / det;
}

/* ellipse.vanishing_lines: l = K^-T n for an upper-triangular K */
static void vanishing_line(const double *K, const double *n, double *l)
{
    l[0] = n[0] / K[0];
    l[1] = (n[1] - K[1] * l[0]) / K[4];
    l[2] = n[2] - K[2] * l[0] - K[5] * l[1];
}

/* stereo._normal_correction of pair k (see its docstring) */
static void correct_pair(const double *C, const double *w, const double *KL, const double *KR,
                         const double *Rrl, Py_ssize_t P, Py_ssize_t k, double *UL, double *UR,
                         double *normal, unsigned char *ok_out)
{
    double Q[9], l1[3], l2[3], c1[3], c2[3], r1[3], r2[3], n[3], nR[3], lL[3], lR[3];
    cone_of(C + 9 * k, KL, Q);
    int okL = cone_normals(Q, l1, l2);
    cone_of(C + 9 * (P + k), KR, Q);
    int okR = cone_normals(Q, c1, c2);
    for (int j = 0; j < 3; j++) {  /* R_rl^T c: the right candidates in the left frame */
        r1[j] = c1[0] * Rrl[j] + c1[1] * Rrl[3 + j] + c1[2] * Rrl[6 + j];
        r2[j] = c2[0] * Rrl[j] + c2[1] * Rrl[3 + j] + c2[2] * Rrl[6 + j];
    }
    const double *L[2] = {l1, l2}, *Rr[2] = {r1, r2};
    int best = 0;
    double bd = -INFINITY;
    for (int m = 0; m < 4; m++) {  /* the best-agreeing candidates, the first maximum */
        const double *a = L[m / 2], *b = Rr[m % 2];
        double dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        if (isnan(dot)) { best = m; break; }  /* np.argmax: a NaN wins */
        if (dot > bd) { bd = dot; best = m; }
    }
    double nn = 0;
    for (int j = 0; j < 3; j++) { n[j] = L[best / 2][j] + Rr[best % 2][j]; nn += n[j] * n[j]; }
    nn = sqrt(nn);
    for (int j = 0; j < 3; j++) n[j] /= nn;
    for (int j = 0; j < 3; j++) nR[j] = n[0] * Rrl[3 * j] + n[1] * Rrl[3 * j + 1] + n[2] * Rrl[3 * j + 2];
    int ok = okL && okR;
    ok_out[k] = (unsigned char)ok;
    for (int j = 0; j < 3; j++) normal[3 * k + j] = n[j];
    if (!ok) return;
    vanishing_line(KL, n, lL);
    vanishing_line(KR, nR, lR);
    double so[2], si[2];
    pole_shift(C + 9 * k, lL, so);            /* left outer, left inner */
    pole_shift(C + 9 * (2 * P + k), lL, si);
    for (int j = 0; j < 2; j++) UL[2 * k + j] += w[2 * k] * so[j] + w[2 * k + 1] * si[j];
    pole_shift(C + 9 * (P + k), lR, so);      /* right outer, right inner */
    pole_shift(C + 9 * (3 * P + k), lR, si);
    for (int j = 0; j < 2; j++) UR[2 * k + j] += w[2 * (P + k)] * so[j] + w[2 * (P + k) + 1] * si[j];
}

PyDoc_STRVAR(normal_correction_doc,
"normal_correction(C, w, K_left, K_right, R_right_from_left, UL, UR, normals, ok) -> None\n\n"
"hil.vision.stereo._normal_correction for P pairs: C (4P, 3, 3) the paired conics in ideal pixels\n"
"(left outer, right outer, left inner, right inner), w (2P, 2) the centre weights (left then\n"
"right), K_left / K_right (3, 3) upper triangular, R_right_from_left (3, 3); moves the ideal\n"
"centres UL, UR (P, 2) px in place where both views gave a normal, writes normals (P, 3)\n"
"(optical frame) and ok (P,) bool.");

static PyObject *k_normal_correction(PyObject *self, PyObject *args)
{
    PyObject *o[9];
    if (!PyArg_ParseTuple(args, "OOOOOOOOO:normal_correction", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5],
                          &o[6], &o[7], &o[8])) {
        return NULL;
    }
    BufSet bs = {.count = 0};
    PyObject *ret = NULL;
    Py_ssize_t sh[3] = {-1, 2, -1}, got[3];
    double *UL = get_buf(&bs, o[5], "UL", 'd', 2, sh, 1, got);
    if (!UL) goto done;
    Py_ssize_t P = got[0];
    Py_ssize_t shP2[2] = {P, 2}, sh4[3] = {4 * P, 3, 3}, sh22[2] = {2 * P, 2}, sh33[2] = {3, 3};
    Py_ssize_t shP3[2] = {P, 3}, shP[1] = {P};
    double *UR = get_buf(&bs, o[6], "UR", 'd', 2, shP2, 1, NULL);
    const double *C = UR ? get_buf(&bs, o[0], "C", 'd', 3, sh4, 0, NULL) : NULL;
    const double *w = C ? get_buf(&bs, o[1], "w", 'd', 2, sh22, 0, NULL) : NULL;
    const double *KL = w ? get_buf(&bs, o[2], "K_left", 'd', 2, sh33, 0, NULL) : NULL;
    const double *KR = KL ? get_buf(&bs, o[3], "K_right", 'd', 2, sh33, 0, NULL) : NULL;
    const double *R = KR ? get_buf(&bs, o[4], "R_right_from_left", 'd', 2, sh33, 0, NULL) : NULL;
    double *normals = R ? get_buf(&bs, o[7], "normals", 'd', 2, shP3, 1, NULL) : NULL;
    unsigned char *ok = normals ? get_buf(&bs, o[8], "ok", '?', 1, shP, 1, NULL) : NULL;
    if (!ok) goto done;
    for (Py_ssize_t k = 0; k < P; k++) {
        correct_pair(C, w, KL, KR, R, P, k, UL, UR, normals, ok);
    }
    ret = Py_NewRef(Py_None);
done:
    bufs_release(&bs);
    return ret;
}

/* ---- stereo: DLT triangulation ------------------------------------------------------------ */

/* The right singular vector of the smallest singular value of a 4x4 matrix (row-major), by
 * one-sided Jacobi rotations (Hestenes; Demmel & Veselic 1992: high relative accuracy). Two
 * columns are orthogonal once |<u_p, u_q>| <= eps |u_p| |u_q| with eps the machine epsilon, their
 * convergence test: a tighter threshold is never met by rounded arithmetic and ran every solve to
 * the 40-sweep cap (~3.5 us a point instead of ~0.6 us, the same vector). */
static void null_vector4(const double *A, double *x)
{
    double U[4][4], V[4][4];
    for (int i = 0; i < 4; i++)
        for (int j = 0; j < 4; j++) {
            U[i][j] = A[4 * i + j];
            V[i][j] = i == j ? 1.0 : 0.0;
        }
    for (int sweep = 0; sweep < 40; sweep++) {
        int rotated = 0;
        for (int p = 0; p < 3; p++)
            for (int q = p + 1; q < 4; q++) {
                double al = 0, be = 0, ga = 0;
                for (int i = 0; i < 4; i++) {
                    al += U[i][p] * U[i][p];
                    be += U[i][q] * U[i][q];
                    ga += U[i][p] * U[i][q];
                }
                if (ga == 0.0 || fabs(ga) <= DBL_EPSILON * sqrt(al * be)) continue;
                rotated = 1;
                double zeta = (be - al) / (2.0 * ga);
                double t = 1.0 / (fabs(zeta) + sqrt(1.0 + zeta * zeta));
                if (zeta < 0) t = -t;
                double c = 1.0 / sqrt(1.0 + t * t), sn = c * t;
                for (int i = 0; i < 4; i++) {
                    double up = U[i][p], uq = U[i][q];
                    U[i][p] = c * up - sn * uq;
                    U[i][q] = sn * up + c * uq;
                    double vp = V[i][p], vq = V[i][q];
                    V[i][p] = c * vp - sn * vq;
                    V[i][q] = sn * vp + c * vq;
                }
            }
        if (!rotated) break;
    }
    int best = 0;
    double bn = INFINITY;
    for (int j = 0; j < 4; j++) {
        double nn = 0;
        for (int i = 0; i < 4; i++) nn += U[i][j] * U[i][j];
        if (nn < bn) { bn = nn; best = j; }
    }
    for (int i = 0; i < 4; i++) x[i] = V[i][best];
}

PyDoc_STRVAR(triangulate_dlt_doc,
"triangulate_dlt(P_left, P_right, uv_left, uv_right, points, ok) -> None\n\n"
"hil.geometry.triangulation.triangulate_dlt (Hartley & Zisserman 12.2, rows equilibrated) of N\n"
"correspondences: P_left / P_right (3, 4) float64, uv_left / uv_right (N, 2) undistorted px;\n"
"writes points (N, 3) mm and ok (N,) bool (False: the point is at infinity, |w| <= 1e-12 |X|).");

static PyObject *k_triangulate_dlt(PyObject *self, PyObject *args)
{
    PyObject *o[6];
    if (!PyArg_ParseTuple(args, "OOOOOO:triangulate_dlt", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5])) {
        return NULL;
    }
    BufSet bs = {.count = 0};
    PyObject *ret = NULL;
    Py_ssize_t sh34[2] = {3, 4}, sh[2] = {-1, 2}, got[2];
    const double *PL = get_buf(&bs, o[0], "P_left", 'd', 2, sh34, 0, NULL);
    const double *PR = PL ? get_buf(&bs, o[1], "P_right", 'd', 2, sh34, 0, NULL) : NULL;
    const double *a = PR ? get_buf(&bs, o[2], "uv_left", 'd', 2, sh, 0, got) : NULL;
    if (!a) goto done;
    Py_ssize_t N = got[0];
    Py_ssize_t shN2[2] = {N, 2}, shN3[2] = {N, 3}, shN[1] = {N};
    const double *b = get_buf(&bs, o[3], "uv_right", 'd', 2, shN2, 0, NULL);
    double *pts = b ? get_buf(&bs, o[4], "points", 'd', 2, shN3, 1, NULL) : NULL;
    unsigned char *ok = pts ? get_buf(&bs, o[5], "ok", '?', 1, shN, 1, NULL) : NULL;
    if (!ok) goto done;
    for (Py_ssize_t k = 0; k < N; k++) {
        double A[16], X[4];
        const double *uv[2] = {a + 2 * k, b + 2 * k}, *Pm[2] = {PL, PR};
        for (int r = 0; r < 4; r++) {  /* u P[2] - P[0], v P[2] - P[1] per camera */
            const double *P = Pm[r / 2];
            double c = uv[r / 2][r % 2], nn = 0;
            for (int j = 0; j < 4; j++) {
                A[4 * r + j] = c * P[8 + j] - P[4 * (r % 2) + j];
                nn += A[4 * r + j] * A[4 * r + j];
            }
            nn = sqrt(nn);
            for (int j = 0; j < 4; j++) A[4 * r + j] /= nn;
        }
        null_vector4(A, X);
        double w = X[3], scale = sqrt(X[0] * X[0] + X[1] * X[1] + X[2] * X[2]);
        ok[k] = (unsigned char)(fabs(w) > 1e-12 * scale);
        for (int j = 0; j < 3; j++) pts[3 * k + j] = X[j] / w;
    }
    ret = Py_NewRef(Py_None);
done:
    bufs_release(&bs);
    return ret;
}

/* ---- stereo: ray gaps ---------------------------------------------------------------------- */

PyDoc_STRVAR(ray_gaps_doc,
"ray_gaps(UL, UR, K_left_inv, K_right_inv, R_right_from_left, right_center, gaps, ok) -> None\n\n"
"The distance (mm) between the left ray through UL (N, 2) ideal px (from the origin) and the right\n"
"ray through UR (from right_center (3,), directions rotated by R_right_from_left^T into the left\n"
"frame): the skew-ray gap of hil.geometry.triangulation.triangulate_midpoint (seed 003 eq 4).\n"
"Writes gaps (N,) and ok (N,) bool (False: a zero direction or parallel rays).");

static PyObject *k_ray_gaps(PyObject *self, PyObject *args)
{
    PyObject *o[8];
    if (!PyArg_ParseTuple(args, "OOOOOOOO:ray_gaps", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7])) {
        return NULL;
    }
    BufSet bs = {.count = 0};
    PyObject *ret = NULL;
    Py_ssize_t sh[2] = {-1, 2}, got[2], sh33[2] = {3, 3}, sh3[1] = {3};
    const double *UL = get_buf(&bs, o[0], "UL", 'd', 2, sh, 0, got);
    if (!UL) goto done;
    Py_ssize_t N = got[0];
    Py_ssize_t shN2[2] = {N, 2}, shN[1] = {N};
    const double *UR = get_buf(&bs, o[1], "UR", 'd', 2, shN2, 0, NULL);
    const double *KLi = UR ? get_buf(&bs, o[2], "K_left_inv", 'd', 2, sh33, 0, NULL) : NULL;
    const double *KRi = KLi ? get_buf(&bs, o[3], "K_right_inv", 'd', 2, sh33, 0, NULL) : NULL;
    const double *R = KRi ? get_buf(&bs, o[4], "R_right_from_left", 'd', 2, sh33, 0, NULL) : NULL;
    const double *ob = R ? get_buf(&bs, o[5], "right_center", 'd', 1, sh3, 0, NULL) : NULL;
    double *gaps = ob ? get_buf(&bs, o[6], "gaps", 'd', 1, shN, 1, NULL) : NULL;
    unsigned char *ok = gaps ? get_buf(&bs, o[7], "ok", '?', 1, shN, 1, NULL) : NULL;
    if (!ok) goto done;
    double w0[3] = {0.0 - ob[0], 0.0 - ob[1], 0.0 - ob[2]};
    for (Py_ssize_t k = 0; k < N; k++) {
        double xl[3] = {UL[2 * k], UL[2 * k + 1], 1.0}, xr[3] = {UR[2 * k], UR[2 * k + 1], 1.0};
        double u[3], e3[3], v[3];
        for (int i = 0; i < 3; i++) {
            u[i] = xl[0] * KLi[3 * i] + xl[1] * KLi[3 * i + 1] + xl[2] * KLi[3 * i + 2];
            e3[i] = xr[0] * KRi[3 * i] + xr[1] * KRi[3 * i + 1] + xr[2] * KRi[3 * i + 2];
        }
        for (int j = 0; j < 3; j++) v[j] = e3[0] * R[j] + e3[1] * R[3 + j] + e3[2] * R[6 + j];
        double nu = sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]);
        double nv = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
        for (int i = 0; i < 3; i++) { u[i] /= nu; v[i] /= nv; }
        double b = u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
        double d = u[0] * w0[0] + u[1] * w0[1] + u[2] * w0[2];
        double e = v[0] * w0[0] + v[1] * w0[1] + v[2] * w0[2];
        double denom = 1.0 - b * b;
        ok[k] = (unsigned char)(nu != 0.0 && nv != 0.0 && denom > 1e-12);
        double s = (b * e - d) / denom, t = (e - b * d) / denom, g = 0;
        for (int i = 0; i < 3; i++) {
            double pa = 0.0 + s * u[i], pb = ob[i] + t * v[i];
            g += (pa - pb) * (pa - pb);
        }
        gaps[k] = sqrt(g);
    }
    ret = Py_NewRef(Py_None);
done:
    bufs_release(&bs);
    return ret;
}

/* ---- stereo: ideal pixels and the local affine maps of distortion --------------------------- */

/* OpenCV's undistortPoints for an identity camera (cvUndistortPointsInternal): the fixed point
 * x = (x_d - tangential(x)) / radial(x) with the criteria (COUNT | EPS, iterations, 1e-15) of
 * hil.vision.camera_model.undistort_normalized; dist = (k1, k2, p1, p2, k3). Returns 0 when the
 * iteration did not converge (a point beyond the lens model's reach, where OpenCV versions differ). */
static int undistort_one(double xd, double yd, const double *k, double *xo, double *yo)
{
    double x0 = xd, y0 = yd, x = xd, y = yd, error = 1.7976931348623157e308;
    for (int j = 0; j < 20 && !(error < 1e-15); j++) {
        double r2 = x * x + y * y;
        double icdist = 1.0 / (1 + ((k[4] * r2 + k[1]) * r2 + k[0]) * r2);
        if (icdist < 0) {
            *xo = xd;
            *yo = yd;
            return 0;
        }
        double deltaX = 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x);
        double deltaY = k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y;
        x = (x0 - deltaX) * icdist;
        y = (y0 - deltaY) * icdist;
        r2 = x * x + y * y;
        double r4 = r2 * r2, r6 = r4 * r2;
        double a1 = 2 * x * y, a2 = r2 + 2 * x * x, a3 = r2 + 2 * y * y;
        double cdist = 1 + k[0] * r2 + k[1] * r4 + k[4] * r6;
        double xp = x * cdist + k[2] * a1 + k[3] * a2;
        double yp = y * cdist + k[2] * a3 + k[3] * a1;
        error = sqrt((xp - xd) * (xp - xd) + (yp - yd) * (yp - yd));
    }
    *xo = x;
    *yo = y;
    return error < 1e-9;
}

/* distorted pixel -> ideal pixel of the same K (hil.vision.camera_model.undistort_pixels) */
static int ideal_pixel(const double *K, const double *dist, double u, double v, double *uo, double *vo)
{
    double yn = (v - K[5]) / K[4];
    double xn = (u - K[2] - K[1] * yn) / K[0];
    double x, y;
    int converged = undistort_one(xn, yn, dist, &x, &y);
    *uo = K[0] * x + K[1] * y + K[2];
    *vo = K[4] * y + K[5];
    return converged;
}

PyDoc_STRVAR(ideal_affines_doc,
"ideal_affines(centers, K, dist, ideal, H, ok) -> None\n\n"
"hil.vision.stereo._ideal_with_affines for a distorted camera: centers (n, 2) distorted px, K (3, 3),\n"
"dist (5,) (k1, k2, p1, p2, k3); writes ideal (n, 2) the undistorted centres (px, same K) and\n"
"H (n, 3, 3) the affine map distorted -> ideal px linearised at each centre by forward differences\n"
"of 1 px, and ok (n,) bool: False where the undistortion did not converge (the caller falls back to\n"
"OpenCV). The undistortion is OpenCV's fixed point with the criteria of\n"
"hil.vision.camera_model.undistort_normalized.");

static PyObject *k_ideal_affines(PyObject *self, PyObject *args)
{
    PyObject *o[6];
    if (!PyArg_ParseTuple(args, "OOOOOO:ideal_affines", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5])) {
        return NULL;
    }
    BufSet bs = {.count = 0};
    PyObject *ret = NULL;
    Py_ssize_t sh[2] = {-1, 2}, got[2], sh33[2] = {3, 3}, sh5[1] = {5};
    const double *c = get_buf(&bs, o[0], "centers", 'd', 2, sh, 0, got);
    if (!c) goto done;
    Py_ssize_t n = got[0];
    Py_ssize_t shn2[2] = {n, 2}, shn33[3] = {n, 3, 3}, shn[1] = {n};
    const double *K = get_buf(&bs, o[1], "K", 'd', 2, sh33, 0, NULL);
    const double *dist = K ? get_buf(&bs, o[2], "dist", 'd', 1, sh5, 0, NULL) : NULL;
    double *ideal = dist ? get_buf(&bs, o[3], "ideal", 'd', 2, shn2, 1, NULL) : NULL;
    double *H = ideal ? get_buf(&bs, o[4], "H", 'd', 3, shn33, 1, NULL) : NULL;
    unsigned char *ok = H ? get_buf(&bs, o[5], "ok", '?', 1, shn, 1, NULL) : NULL;
    if (!ok) goto done;
    for (Py_ssize_t k = 0; k < n; k++) {
        double u = c[2 * k], v = c[2 * k + 1], u0, v0, ux, vx, uy, vy;
        int c0 = ideal_pixel(K, dist, u, v, &u0, &v0);
        int cx = ideal_pixel(K, dist, u + 1.0, v + 0.0, &ux, &vx);
        int cy = ideal_pixel(K, dist, u + 0.0, v + 1.0, &uy, &vy);
        ok[k] = (unsigned char)(c0 && cx && cy);
        double *h = H + 9 * k;
        h[0] = (ux - u0) / 1.0;
        h[3] = (vx - v0) / 1.0;
        h[1] = (uy - u0) / 1.0;
        h[4] = (vy - v0) / 1.0;
        h[2] = u0 - (h[0] * u + h[1] * v);
        h[5] = v0 - (h[3] * u + h[4] * v);
        h[6] = 0.0;
        h[7] = 0.0;
        h[8] = 1.0;
        ideal[2 * k] = u0;
        ideal[2 * k + 1] = v0;
    }
    ret = Py_NewRef(Py_None);
done:
    bufs_release(&bs);
    return ret;
}

PyDoc_STRVAR(conics_to_ideal_doc,
"conics_to_ideal(C, H, out) -> None\n\n"
"hil.vision.stereo._to_ideal_stack: conics C (m, 3, 3) in distorted pixels through their affine\n"
"maps H (m, 3, 3) (last row 0 0 1): out = H^-T C H^-1 scaled to unit Frobenius norm (m, 3, 3).\n"
"A singular map gives a non-finite conic (as numpy's division by a zero determinant).");

static PyObject *k_conics_to_ideal(PyObject *self, PyObject *args)
{
    PyObject *o[3];
    if (!PyArg_ParseTuple(args, "OOO:conics_to_ideal", &o[0], &o[1], &o[2])) {
        return NULL;
    }
    BufSet bs = {.count = 0};
    PyObject *ret = NULL;
    Py_ssize_t sh[3] = {-1, 3, 3}, got[3];
    const double *C = get_buf(&bs, o[0], "C", 'd', 3, sh, 0, got);
    if (!C) goto done;
    Py_ssize_t m = got[0];
    Py_ssize_t shm[3] = {m, 3, 3};
    const double *H = get_buf(&bs, o[1], "H", 'd', 3, shm, 0, NULL);
    double *out = H ? get_buf(&bs, o[2], "out", 'd', 3, shm, 1, NULL) : NULL;
    if (!out) goto done;
    for (Py_ssize_t k = 0; k < m; k++) {
        const double *h = H + 9 * k, *c = C + 9 * k;
        double a = h[0], b = h[1], cc = h[3], d = h[4];
        double det = a * d - b * cc;
        double Hi[9] = {d / det, -b / det, 0.0, -cc / det, a / det, 0.0, 0.0, 0.0, 1.0};
        double tx = h[2], ty = h[5];
        Hi[2] = -(Hi[0] * tx + Hi[1] * ty);
        Hi[5] = -(Hi[3] * tx + Hi[4] * ty);
        double T[9], R[9], s = 0.0;
        for (int i = 0; i < 3; i++) {     /* T = Hi^T C */
            for (int j = 0; j < 3; j++) {
                T[3 * i + j] = Hi[i] * c[j] + Hi[3 + i] * c[3 + j] + Hi[6 + i] * c[6 + j];
            }
        }
        for (int i = 0; i < 3; i++) {     /* R = T Hi */
            for (int j = 0; j < 3; j++) {
                R[3 * i + j] = T[3 * i] * Hi[j] + T[3 * i + 1] * Hi[3 + j] + T[3 * i + 2] * Hi[6 + j];
                s += R[3 * i + j] * R[3 * i + j];
            }
        }
        double nrm = sqrt(s);
        for (int i = 0; i < 9; i++) out[9 * k + i] = R[i] / nrm;
    }
    ret = Py_NewRef(Py_None);
done:
    bufs_release(&bs);
    return ret;
}

/* ---- module ------------------------------------------------------------------------------- */

static PyMethodDef kernel_methods[] = {
    {"ring_geometry", k_ring_geometry, METH_VARARGS, ring_geometry_doc},
    {"ray_maps", k_ray_maps, METH_VARARGS, ray_maps_doc},
    {"ring_edges", k_ring_edges, METH_VARARGS, ring_edges_doc},
    {"fit_ellipses", k_fit_ellipses, METH_VARARGS, fit_ellipses_doc},
    {"normal_correction", k_normal_correction, METH_VARARGS, normal_correction_doc},
    {"ring_check", k_ring_check, METH_VARARGS, ring_check_doc},
    {"triangulate_dlt", k_triangulate_dlt, METH_VARARGS, triangulate_dlt_doc},
    {"ray_gaps", k_ray_gaps, METH_VARARGS, ray_gaps_doc},
    {"ideal_affines", k_ideal_affines, METH_VARARGS, ideal_affines_doc},
    {"conics_to_ideal", k_conics_to_ideal, METH_VARARGS, conics_to_ideal_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef kernel_module = {
    PyModuleDef_HEAD_INIT, "_kernel",
    "Compiled per-ring kernels of hil.vision (ring edges, robust ellipse fits); see _kernel.c.",
    0, kernel_methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__kernel(void)
{
    return PyModuleDef_Init(&kernel_module);
}
