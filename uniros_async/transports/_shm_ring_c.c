/* The compiled twin of uniros_async.transports._shm_ring.RingEnd: one end's side of an shm:// connection's two
 * rings and the operations a frame takes on its usual path (take a frame that is there, poll for one, write and
 * publish one). Same constructor, attributes, methods and results as the Python class; _shm_ring.py holds the
 * layout and the reasons. Built by `pip install` where a C compiler is at hand (setup.py, optional); where it is
 * not, the Python class is used.
 *
 * Why C: at one env, a vector step's overhead is what its lines of Python cost, and these paths run four
 * times a step (a write and a read on each side). In Python they cost 4-5 us a frame; here well under 1 us.
 *
 * Memory order: positions are stored with release and loaded with acquire semantics; between publishing a
 * position and reading the peer's ticket (and between setting a ticket and re-reading a position, in Python) there
 * is a full fence, so that a sleeping peer is never missed (see ShmTransport._wait_readable).
 */
#define _GNU_SOURCE
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <structmember.h>

#include <errno.h>
#include <sched.h>
#include <stddef.h>
#include <stdint.h>
#include <time.h>
#include <unistd.h>

/* indexes into a ctl block viewed as uint64 words (as in _shm_ring.py) */
#define W_POS 0
#define R_POS 8
#define R_TICKET 16
#define W_TICKET 24
#define R_CPU 32
#define CTL_WORDS 33
#define SKIP (UINT64_C(1) << 63)
#define RESTART_BYTES UINT64_C(4096)
#define CPU_HINT_NS INT64_C(1000000)

typedef struct {
    PyObject_HEAD
    Py_buffer rx_ctl_buf, rx_data_buf, tx_ctl_buf, tx_data_buf;
    int held;         /* the four buffers above are held */
    int polling;      /* poll() runs without the GIL: close() must leave the buffers to it */
    int close_asked;  /* close() came while polling: poll() lets the buffers go when it ends */
    PyObject *rx_ro;  /* the read-only view of the rx ring's data, which take_ready() slices */
    uint64_t *rx_ctl, *tx_ctl;
    unsigned char *rx_data, *tx_data;
    uint64_t cap, quarter, max_frame;
    int peer_doorbell;
    /* the state, as in the Python class */
    unsigned long long wpos, rpos, rx_released, signaled_reader, signaled_writer, sent_since_wait;
    long long cpu_said_by;
    unsigned long long frames_sent, bytes_sent, frames_received, bytes_received;
    char rx_fast, tx_fast;
} RingEnd;

static inline uint64_t load_acquire(uint64_t *p) { return __atomic_load_n(p, __ATOMIC_ACQUIRE); }
static inline void store_release(uint64_t *p, uint64_t v) { __atomic_store_n(p, v, __ATOMIC_RELEASE); }
static inline void full_fence(void) { __atomic_thread_fence(__ATOMIC_SEQ_CST); }

/* poll() between its looks: the CPU's spin-wait hint, and sched_yield() once every YIELD_EVERY_NS, so that a
 * frame is seen within a look's time of its arrival (a sched_yield() is a system call, far longer than a look)
 * while another task runnable on this core still gets its turn within microseconds. */
#define YIELD_EVERY_NS 2000
#if defined(__x86_64__) || defined(__i386__)
static inline void cpu_relax(void) { __builtin_ia32_pause(); }
#elif defined(__aarch64__)
static inline void cpu_relax(void) { __asm__ __volatile__("yield"); }
#else
static inline void cpu_relax(void) {}
#endif

static inline int64_t now_ns(void) /* CLOCK_MONOTONIC: time.perf_counter_ns on Linux */
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static void release_buffers(RingEnd *self)
{
    if (self->held) {
        self->held = 0;
        PyBuffer_Release(&self->rx_ctl_buf);
        PyBuffer_Release(&self->rx_data_buf);
        PyBuffer_Release(&self->tx_ctl_buf);
        PyBuffer_Release(&self->tx_data_buf);
    }
    Py_CLEAR(self->rx_ro);
}

static int closed_error(RingEnd *self)
{
    if (self->held)
        return 0;
    PyErr_SetString(PyExc_ValueError, "the ring end is closed");
    return -1;
}

static int ring_doorbell(RingEnd *self) /* os.eventfd_write(peer_doorbell, 1) */
{
    uint64_t one = 1;
    for (;;) {
        ssize_t r = write(self->peer_doorbell, &one, sizeof one);
        if (r == (ssize_t)sizeof one)
            return 0;
        if (r < 0 && errno == EINTR) {
            if (PyErr_CheckSignals() < 0)
                return -1;
            continue;
        }
        PyErr_SetFromErrno(PyExc_OSError);
        return -1;
    }
}

/* Store a position (release), then, after a full fence, ring the peer if its ticket says it sleeps and it was not
 * rung for that ticket yet: the store-fence-load that no lost wake-up rests on (ShmTransport._wait_readable). */
static int store_and_wake(RingEnd *self, uint64_t *pos, uint64_t value, uint64_t *ticket_word,
                          unsigned long long *signaled)
{
    store_release(pos, value);
    full_fence();
    uint64_t ticket = load_acquire(ticket_word);
    if ((ticket & 1) && ticket != *signaled) {
        *signaled = ticket;
        return ring_doorbell(self);
    }
    return 0;
}

static int release_rx_impl(RingEnd *self) /* give the space up to rpos back; wake a writer waiting for space */
{
    self->rx_released = self->rpos;
    return store_and_wake(self, &self->rx_ctl[R_POS], self->rpos, &self->rx_ctl[W_TICKET], &self->signaled_writer);
}

static int publish_impl(RingEnd *self, uint64_t wpos) /* make the tx ring visible up to wpos; wake a sleeping reader */
{
    self->wpos = wpos;
    return store_and_wake(self, &self->tx_ctl[W_POS], wpos, &self->tx_ctl[R_TICKET], &self->signaled_reader);
}

static int commit_impl(RingEnd *self, uint64_t n, uint64_t rec, uint64_t skip)
{
    if (publish_impl(self, self->wpos + skip + rec) < 0)
        return -1;
    self->sent_since_wait += n;
    self->frames_sent += 1;
    self->bytes_sent += n;
    int64_t now = now_ns();
    if (now > self->cpu_said_by) {
        self->cpu_said_by = now + CPU_HINT_NS;
        __atomic_store_n(&self->rx_ctl[R_CPU], (uint64_t)(sched_getcpu() + 1), __ATOMIC_RELAXED);
    }
    return 0;
}

/* 1 and (*off, *skip) when a record of rec bytes has a place, else 0 */
static int place_impl(RingEnd *self, uint64_t rec, uint64_t *off, uint64_t *skip)
{
    uint64_t cap = self->cap, wpos = self->wpos;
    uint64_t used = wpos - load_acquire(&self->tx_ctl[R_POS]);
    if (used > cap)
        return 0; /* a reader past our writes: never, unless the peer broke the ring; no room */
    uint64_t free_ = cap - used, o = wpos % cap, tail = cap - o;
    *off = o;
    if (rec >= RESTART_BYTES && tail + rec <= free_ && used <= self->quarter) {
        *skip = tail;
        return 1;
    }
    if (rec <= tail && rec <= free_) {
        *skip = 0;
        return 1;
    }
    if (tail + rec <= free_) {
        *skip = tail;
        return 1;
    }
    if (rec <= free_) {
        *skip = 0;
        return 1;
    }
    return 0;
}

/* ------------------------------------------------------------------------------------------------ methods */

static PyObject *RingEnd_take_ready(RingEnd *self, PyObject *Py_UNUSED(ignored))
{
    if (!self->rx_fast || !self->held)
        Py_RETURN_NONE;
    uint64_t rpos = self->rpos;
    if (rpos != self->rx_released && release_rx_impl(self) < 0)
        return NULL;
    uint64_t avail = load_acquire(&self->rx_ctl[W_POS]) - rpos, cap = self->cap;
    if (avail > 0 && avail <= cap) {
        const uint64_t *q = (const uint64_t *)self->rx_data;
        uint64_t off = rpos % cap;
        uint64_t n = q[off >> 3];
        if (n == SKIP && avail > cap - off) {
            rpos += cap - off;
            avail -= cap - off;
            off = 0;
            n = q[0];
        }
        if (n <= self->max_frame) {
            uint64_t rec = 8 + ((n + 7) & ~UINT64_C(7)), end = off + 8 + n;
            if (rec <= avail && end <= cap) {
                PyObject *view = PySequence_GetSlice(self->rx_ro, (Py_ssize_t)(off + 8), (Py_ssize_t)end);
                if (view == NULL)
                    return NULL;
                self->rpos = rpos + rec;
                self->frames_received += 1;
                self->bytes_received += n;
                return view;
            }
        }
    }
    Py_RETURN_NONE;
}

static PyObject *RingEnd_release_rx(RingEnd *self, PyObject *Py_UNUSED(ignored))
{
    if (closed_error(self) < 0 || release_rx_impl(self) < 0)
        return NULL;
    Py_RETURN_NONE;
}

static PyObject *RingEnd_poll(RingEnd *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 2) {
        PyErr_Format(PyExc_TypeError, "poll() takes 2 arguments (deadline_ns, look_at_ns), %zd given", nargs);
        return NULL;
    }
    long long deadline = PyLong_AsLongLong(args[0]);
    if (deadline == -1 && PyErr_Occurred())
        return NULL;
    long long look_at = PyLong_AsLongLong(args[1]);
    if (look_at == -1 && PyErr_Occurred())
        return NULL;
    if (!self->held)
        return PyLong_FromLong(0);
    uint64_t *w = &self->rx_ctl[W_POS];
    uint64_t rpos = self->rpos;
    long result;
    self->polling = 1;
    Py_BEGIN_ALLOW_THREADS /* as os.sched_yield does between the Python class's polls */
    int64_t next_yield = now_ns() + YIELD_EVERY_NS;
    for (;;) {
        if (load_acquire(w) != rpos) {
            result = 1;
            break;
        }
        int64_t now = now_ns();
        if (now > look_at) {
            result = 2;
            break;
        }
        if (now > deadline) {
            result = 0;
            break;
        }
        if (now >= next_yield) {
            sched_yield();
            next_yield = now_ns() + YIELD_EVERY_NS;
        } else {
            cpu_relax();
        }
    }
    Py_END_ALLOW_THREADS
    self->polling = 0;
    if (self->close_asked)
        release_buffers(self);
    return PyLong_FromLong(result);
}

static PyObject *RingEnd_try_send(RingEnd *self, PyObject *frame)
{
    if (!self->tx_fast || !self->held)
        Py_RETURN_FALSE;
    Py_buffer buf;
    const char *src;
    uint64_t n;
    int have_buf = 0;
    if (PyBytes_CheckExact(frame)) {
        src = PyBytes_AS_STRING(frame);
        n = (uint64_t)PyBytes_GET_SIZE(frame);
    } else {
        if (PyObject_GetBuffer(frame, &buf, PyBUF_SIMPLE) < 0)
            return NULL;
        have_buf = 1;
        src = buf.buf;
        n = (uint64_t)buf.len;
    }
    PyObject *result = Py_False;
    uint64_t off, skip, cap = self->cap;
    if (n <= self->max_frame) {
        uint64_t rec = 8 + ((n + 7) & ~UINT64_C(7));
        if (rec <= cap && place_impl(self, rec, &off, &skip)) {
            uint64_t *q = (uint64_t *)self->tx_data;
            if (skip) {
                q[off >> 3] = SKIP;
                off = 0;
            }
            q[off >> 3] = n;
            uint64_t start = off + 8;
            if (start == cap) /* the header took the ring's last 8 bytes */
                start = 0;
            if (start + n <= cap) {
                memcpy(self->tx_data + start, src, n);
            } else { /* wraps around the end of the ring (the reader copies it) */
                uint64_t first = cap - start;
                memcpy(self->tx_data + start, src, first);
                memcpy(self->tx_data, src + first, n - first);
            }
            result = commit_impl(self, n, rec, skip) < 0 ? NULL : Py_True;
        }
    }
    if (have_buf)
        PyBuffer_Release(&buf);
    Py_XINCREF(result);
    return result;
}

static PyObject *RingEnd_place(RingEnd *self, PyObject *arg)
{
    if (closed_error(self) < 0)
        return NULL;
    unsigned long long rec = PyLong_AsUnsignedLongLong(arg);
    if (rec == (unsigned long long)-1 && PyErr_Occurred())
        return NULL;
    uint64_t off, skip;
    if (!place_impl(self, rec, &off, &skip))
        Py_RETURN_NONE;
    return Py_BuildValue("(KK)", (unsigned long long)off, (unsigned long long)skip);
}

static PyObject *RingEnd_commit(RingEnd *self, PyObject *const *args, Py_ssize_t nargs)
{
    if (nargs != 3) {
        PyErr_Format(PyExc_TypeError, "commit() takes 3 arguments (n, rec, skip), %zd given", nargs);
        return NULL;
    }
    unsigned long long v[3];
    for (int i = 0; i < 3; i++) {
        v[i] = PyLong_AsUnsignedLongLong(args[i]);
        if (v[i] == (unsigned long long)-1 && PyErr_Occurred())
            return NULL;
    }
    if (closed_error(self) < 0 || commit_impl(self, v[0], v[1], v[2]) < 0)
        return NULL;
    Py_RETURN_NONE;
}

static PyObject *RingEnd_publish(RingEnd *self, PyObject *arg)
{
    unsigned long long wpos = PyLong_AsUnsignedLongLong(arg);
    if (wpos == (unsigned long long)-1 && PyErr_Occurred())
        return NULL;
    if (closed_error(self) < 0 || publish_impl(self, wpos) < 0)
        return NULL;
    Py_RETURN_NONE;
}

static PyObject *RingEnd_close(RingEnd *self, PyObject *Py_UNUSED(ignored))
{
    self->rx_fast = self->tx_fast = 0;
    if (self->polling) /* another thread polls without the GIL: it lets the buffers go when it ends */
        self->close_asked = 1;
    else
        release_buffers(self);
    Py_RETURN_NONE;
}

/* ----------------------------------------------------------------------------------------------- the type */

static int get_view(PyObject *views, const char *name, Py_buffer *out, int flags)
{
    PyObject *obj = PyObject_GetAttrString(views, name);
    if (obj == NULL)
        return -1;
    int r = PyObject_GetBuffer(obj, out, flags);
    Py_DECREF(obj);
    return r;
}

static int RingEnd_init(RingEnd *self, PyObject *args, PyObject *kwds)
{
    static char *kwlist[] = {"rx", "tx", "max_frame", "peer_doorbell", NULL};
    PyObject *rx, *tx;
    unsigned long long max_frame;
    int peer_doorbell;
    if (!PyArg_ParseTupleAndKeywords(args, kwds, "OOKi:RingEnd", kwlist, &rx, &tx, &max_frame, &peer_doorbell))
        return -1;
    if (self->held || self->rx_ro != NULL) {
        PyErr_SetString(PyExc_RuntimeError, "RingEnd.__init__ called twice");
        return -1;
    }
    Py_buffer b[4];
    int got = 0;
    const char *names[4] = {"ctl", "data", "ctl", "data"};
    for (; got < 4; got++) {
        if (get_view(got < 2 ? rx : tx, names[got], &b[got], PyBUF_WRITABLE) < 0)
            goto fail;
    }
    uint64_t cap = (uint64_t)b[1].len;
    if ((uint64_t)b[3].len != cap || cap == 0 || cap % 8) {
        PyErr_Format(PyExc_ValueError, "rings of %zd and %zd bytes: expected two of one size, a multiple of 8",
                     b[1].len, b[3].len);
        goto fail;
    }
    for (int i = 0; i < 4; i++) {
        if ((uintptr_t)b[i].buf % 8 || (i % 2 == 0 && b[i].len < CTL_WORDS * 8)) {
            PyErr_SetString(PyExc_ValueError, "a ctl block or ring is misaligned or too small for the layout");
            goto fail;
        }
    }
    self->rx_ro = PyObject_GetAttrString(rx, "data_ro");
    if (self->rx_ro == NULL)
        goto fail;
    self->rx_ctl_buf = b[0];
    self->rx_data_buf = b[1];
    self->tx_ctl_buf = b[2];
    self->tx_data_buf = b[3];
    self->held = 1;
    self->rx_ctl = b[0].buf;
    self->rx_data = b[1].buf;
    self->tx_ctl = b[2].buf;
    self->tx_data = b[3].buf;
    self->cap = cap;
    self->quarter = cap >> 2;
    self->max_frame = max_frame;
    self->peer_doorbell = peer_doorbell;
    self->rpos = self->rx_released = load_acquire(&self->rx_ctl[R_POS]);
    self->wpos = load_acquire(&self->tx_ctl[W_POS]);
    self->rx_fast = self->tx_fast = 1;
    return 0;
fail:
    for (int i = 0; i < got; i++)
        PyBuffer_Release(&b[i]);
    return -1;
}

static void RingEnd_dealloc(RingEnd *self)
{
    release_buffers(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static PyMethodDef RingEnd_methods[] = {
    {"take_ready", (PyCFunction)RingEnd_take_ready, METH_NOARGS,
     "The next frame if rx_fast and it is already there, whole and contiguous: a read-only view, else None."},
    {"release_rx", (PyCFunction)RingEnd_release_rx, METH_NOARGS,
     "Give the space up to rpos back to the writer, and ring its doorbell if it waits for space."},
    {"poll", (PyCFunction)(void (*)(void))RingEnd_poll, METH_FASTCALL,
     "poll(deadline_ns, look_at_ns): 1 when data is past rpos, 2 past look_at_ns, 0 past deadline_ns."},
    {"try_send", (PyCFunction)RingEnd_try_send, METH_O,
     "Write and publish a frame if that needs no waiting; True if sent, False if nothing was written."},
    {"place", (PyCFunction)RingEnd_place, METH_O,
     "place(rec): (offset, skip) for a record of rec bytes, or None while the ring lacks room."},
    {"commit", (PyCFunction)(void (*)(void))RingEnd_commit, METH_FASTCALL,
     "commit(n, rec, skip): publish a record that is in place, ring the reader if it sleeps, count it."},
    {"publish", (PyCFunction)RingEnd_publish, METH_O, "publish(wpos): make everything up to wpos visible."},
    {"close", (PyCFunction)RingEnd_close, METH_NOARGS,
     "Stop both fast paths and let go of the ring's buffers; the other methods then raise ValueError."},
    {NULL, NULL, 0, NULL},
};

#define STATE(name, type) {#name, type, offsetof(RingEnd, name), 0, NULL}
static PyMemberDef RingEnd_members[] = {
    STATE(wpos, T_ULONGLONG),
    STATE(rpos, T_ULONGLONG),
    STATE(rx_released, T_ULONGLONG),
    STATE(signaled_reader, T_ULONGLONG),
    STATE(signaled_writer, T_ULONGLONG),
    STATE(sent_since_wait, T_ULONGLONG),
    STATE(cpu_said_by, T_LONGLONG),
    STATE(frames_sent, T_ULONGLONG),
    STATE(bytes_sent, T_ULONGLONG),
    STATE(frames_received, T_ULONGLONG),
    STATE(bytes_received, T_ULONGLONG),
    STATE(rx_fast, T_BOOL),
    STATE(tx_fast, T_BOOL),
    {NULL, 0, 0, 0, NULL},
};

static PyTypeObject RingEndType = {
    PyVarObject_HEAD_INIT(NULL, 0)
    .tp_name = "uniros_async.transports._shm_ring_c.RingEnd",
    .tp_doc = "One end's side of an shm:// connection's two rings (the compiled twin of _shm_ring.RingEnd).",
    .tp_basicsize = sizeof(RingEnd),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)RingEnd_init,
    .tp_dealloc = (destructor)RingEnd_dealloc,
    .tp_methods = RingEnd_methods,
    .tp_members = RingEnd_members,
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT,
    .m_name = "uniros_async.transports._shm_ring_c",
    .m_doc = "The compiled RingEnd of shm:// (see _shm_ring.py).",
    .m_size = -1,
};

PyMODINIT_FUNC PyInit__shm_ring_c(void)
{
    if (PyType_Ready(&RingEndType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&module);
    if (m == NULL)
        return NULL;
    if (PyModule_AddObjectRef(m, "RingEnd", (PyObject *)&RingEndType) < 0
        || PyModule_AddIntConstant(m, "RESTART_BYTES", (long)RESTART_BYTES) < 0
        || PyModule_AddIntConstant(m, "CPU_HINT_NS", (long)CPU_HINT_NS) < 0
        || PyModule_AddIntConstant(m, "W_POS", W_POS) < 0 || PyModule_AddIntConstant(m, "R_POS", R_POS) < 0
        || PyModule_AddIntConstant(m, "R_TICKET", R_TICKET) < 0
        || PyModule_AddIntConstant(m, "W_TICKET", W_TICKET) < 0 || PyModule_AddIntConstant(m, "R_CPU", R_CPU) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
