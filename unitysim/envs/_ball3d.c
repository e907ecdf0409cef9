/* 3DBall's actions, physics step and observation in C: the optional fast path of
 * unitysim/envs/ball3d.py, whose Ball3D._act, _move and _observe are the numpy twins and
 * explain every row and constant. Both must stay the same equations in the same order:
 * tests/unitysim/test_ball3d.py compares them to the last bit.
 *
 * Why: a numpy step is ~30 calls on 12-element arrays, ~1 us each and 2-4 times that in a
 * player that wakes cold every exchange; this loop takes ~1 us for all agents. setup.py
 * builds it as an optional extension; without a C compiler the numpy twins run. It is
 * compiled without floating-point contraction, so every product is rounded on its own as
 * numpy rounds it; sin and cos come from libm, as numpy's do here (tan is sin / cos in
 * both: numpy's own SIMD tan rounds differently). */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdbool.h>
#include <string.h>

/* Takes a writable C-contiguous buffer of `format` (one struct char) shaped (rows, cols),
 * or (rows,) where cols is 0; -1 with an error set naming `what` if it is not one. */
static int take(PyObject *obj, Py_buffer *view, const char *format, Py_ssize_t rows,
                Py_ssize_t cols, const char *what) {
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE | PyBUF_FORMAT) < 0) {
        PyErr_Format(PyExc_ValueError, "%s: need a writable C-contiguous array", what);
        return -1;
    }
    const char *got = view->format ? view->format : "B";
    const int ndim = cols ? 2 : 1;
    if (strcmp(got, format) != 0 || view->ndim != ndim || view->shape[0] != rows ||
        (cols && view->shape[1] != cols)) {
        if (cols)
            PyErr_Format(PyExc_ValueError, "%s: need a (%zd, %zd) array of format '%s'", what,
                         rows, cols, format);
        else
            PyErr_Format(PyExc_ValueError, "%s: need a (%zd,) array of format '%s'", what, rows,
                         format);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

/* The number of agents, n, of an (8, n) state (which `take` then checks in full). */
static Py_ssize_t agents_in(PyObject *state) {
    Py_buffer view;
    Py_ssize_t n = -1;
    if (PyObject_GetBuffer(state, &view, PyBUF_ND) == 0) {
        n = view.ndim == 2 ? view.shape[1] : -1;
        PyBuffer_Release(&view);
    }
    if (n < 0) PyErr_SetString(PyExc_ValueError, "state: need an (8, n) float64 array");
    return n;
}

/* Checks that `name` got `want` arguments and reads those from `first` on as doubles into
 * `out`; -1 with an error set if not. */
static int arguments(const char *name, PyObject *const *args, Py_ssize_t nargs,
                     Py_ssize_t want, Py_ssize_t first, double *out) {
    if (nargs != want) {
        PyErr_Format(PyExc_TypeError, "%s takes %zd arguments", name, want);
        return -1;
    }
    for (Py_ssize_t k = first; k < want; k++) {
        out[k - first] = PyFloat_AsDouble(args[k]);
        if (out[k - first] == -1.0 && PyErr_Occurred()) return -1;
    }
    return 0;
}

static double maximum(double a, double b) { /* np.maximum: NaN wins */
    if (isnan(a) || isnan(b)) return isnan(a) ? a : b;
    return a > b ? a : b;
}

/* physics_step(state, turn, reach, reward, fell, radius, fall_dv, slope_dv, shove_dv,
 *              dt, max_sigma, half_width, resting_tolerance) -> number of balls that fell
 * state: (8, n) float64; turn: (2, n) float64; reach: (n,) float64; reward: (n,) float32;
 * fell: (n,) bool, written. */
static PyObject *physics_step(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    double c[8];
    if (arguments("physics_step", args, nargs, 13, 5, c) < 0) return NULL;
    const double radius = c[0], fall_dv = c[1], slope_dv = c[2], shove_dv = c[3];
    const double dt = c[4], max_sigma = c[5], half_width = c[6], tolerance = c[7];

    const Py_ssize_t n = agents_in(args[0]);
    if (n < 0) return NULL;
    Py_buffer views[5];
    int held = 0;
    PyObject *result = NULL;
    static const char *formats[5] = {"d", "d", "d", "f", "?"};
    static const char *names[5] = {"state", "turn", "reach", "reward", "fell"};
    const Py_ssize_t rows[5] = {8, 2, n, n, n}, cols[5] = {n, n, 0, 0, 0};
    for (; held < 5; held++)
        if (take(args[held], &views[held], formats[held], rows[held], cols[held], names[held]))
            goto done;

    double *s = views[0].buf;
    double *sigma0 = s, *sigma1 = s + n, *x = s + 2 * n, *z = s + 3 * n, *y = s + 4 * n;
    double *vx = s + 5 * n, *vz = s + 6 * n, *vy = s + 7 * n;
    const double *turn0 = views[1].buf, *turn1 = (const double *)views[1].buf + n;
    double *rch = views[2].buf;
    float *rew = views[3].buf;
    bool *out = views[4].buf;
    long fallen = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        /* Turn while inside the limit in the direction of the turn (Unity's rule). */
        const double d0 = (double)((turn0[i] > 0) - (turn0[i] < 0));
        const double d1 = (double)((turn1[i] > 0) - (turn1[i] < 0));
        const double t0 = turn0[i] * (double)(d0 * sigma0[i] < max_sigma);
        const double t1 = turn1[i] * (double)(d1 * sigma1[i] < max_sigma);
        sigma0[i] += t0;
        sigma1[i] += t1;
        const double sin0 = sin(sigma0[i]), sin1 = sin(sigma1[i]);
        const double tan0 = sin0 / cos(sigma0[i]), tan1 = sin1 / cos(sigma1[i]);

        double top = x[i] * tan0 + z[i] * tan1;
        top += radius;
        const bool over = rch[i] <= half_width;
        const bool resting = over && (y[i] - top <= tolerance);

        double roll0 = sin0 * slope_dv, roll1 = sin1 * slope_dv;
        roll0 += t0 * shove_dv;
        roll1 += t1 * shove_dv;
        vx[i] += roll0 * (double)resting;
        vz[i] += roll1 * (double)resting;
        vy[i] += -fall_dv;
        x[i] += vx[i] * dt;
        z[i] += vz[i] * dt;
        y[i] += vy[i] * dt;
        if (over && y[i] < top) {
            y[i] = top;
            vy[i] = 0.0;
        }
        rch[i] = maximum(fabs(x[i]), fabs(z[i]));
        out[i] = rch[i] > 3.0 || y[i] < -2.0;
        rew[i] = out[i] ? -1.0f : 0.1f;
        fallen += out[i];
    }
    result = PyLong_FromLong(fallen);
done:
    while (held > 0) PyBuffer_Release(&views[--held]);
    return result;
}

/* act(actions, turn, turn_z, turn_x): turn (2, n) float64 <- Ball3D._act of the
 * (n, 2) float32 actions (any strides): clamped to [-1, 1], NaN as no turn, times the
 * radians per step of each axis. */
static PyObject *act(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    double rate[2];
    if (arguments("act", args, nargs, 4, 2, rate) < 0) return NULL;
    Py_buffer actions, turn;
    if (PyObject_GetBuffer(args[0], &actions, PyBUF_RECORDS_RO) < 0) return NULL;
    const Py_ssize_t n = actions.ndim == 2 ? actions.shape[0] : -1;
    if (n < 0 || actions.shape[1] != 2 || strcmp(actions.format, "f") != 0) {
        PyErr_SetString(PyExc_ValueError, "actions: need an (n, 2) float32 array");
        PyBuffer_Release(&actions);
        return NULL;
    }
    if (take(args[1], &turn, "d", 2, n, "turn") < 0) {
        PyBuffer_Release(&actions);
        return NULL;
    }
    const char *row = actions.buf;
    double *out = turn.buf;
    for (Py_ssize_t i = 0; i < n; i++, row += actions.strides[0]) {
        for (int k = 0; k < 2; k++) {
            float a = *(const float *)(row + k * actions.strides[1]);
            a = isnan(a) ? 0.0f : a > 1.0f ? 1.0f : a < -1.0f ? -1.0f : a;
            out[k * n + i] = (double)a * rate[k];
        }
    }
    PyBuffer_Release(&turn);
    PyBuffer_Release(&actions);
    Py_RETURN_NONE;
}

/* observe(state, obs): obs (n, 8) float32 <- the observation of Ball3D._observe. */
static PyObject *observe(PyObject *self, PyObject *const *args, Py_ssize_t nargs) {
    (void)self;
    if (arguments("observe", args, nargs, 2, 2, NULL) < 0) return NULL;
    const Py_ssize_t n = agents_in(args[0]);
    if (n < 0) return NULL;
    Py_buffer state, obs;
    if (take(args[0], &state, "d", 8, n, "state") < 0) return NULL;
    if (take(args[1], &obs, "f", n, 8, "obs") < 0) {
        PyBuffer_Release(&state);
        return NULL;
    }
    const double *s = state.buf;
    float *o = obs.buf;
    for (Py_ssize_t i = 0; i < n; i++, o += 8) {
        /* quaternion z and x components of the tilts; position x, y, z; velocity x, y, z */
        o[0] = (float)(sin(s[i] * 0.5) * -1.0); /* as numpy: times the axis sign */
        o[1] = (float)sin(s[n + i] * 0.5);
        o[2] = (float)s[2 * n + i];
        o[3] = (float)s[4 * n + i];
        o[4] = (float)s[3 * n + i];
        o[5] = (float)s[5 * n + i];
        o[6] = (float)s[7 * n + i];
        o[7] = (float)s[6 * n + i];
    }
    PyBuffer_Release(&obs);
    PyBuffer_Release(&state);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"act", (PyCFunction)(void (*)(void))act, METH_FASTCALL,
     "Each agent's turn per physics step from its (clamped) actions."},
    {"observe", (PyCFunction)(void (*)(void))observe, METH_FASTCALL,
     "The 3DBall observation of every agent, written into an (n, 8) float32 array."},
    {"physics_step", (PyCFunction)(void (*)(void))physics_step, METH_FASTCALL,
     "One 3DBall physics step for every agent; returns how many balls fell."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_ball3d", "Compiled 3DBall physics (optional).", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__ball3d(void) { return PyModule_Create(&module); }
