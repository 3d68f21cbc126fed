# cython: language_level=3, boundscheck=False, wraparound=False, initializedcheck=False, cdivision=True
"""The front of ``mocapd run --workers N`` routing ZeroMQ messages in C: each ``[topic, payload]``
message of the poses socket goes, undecoded, to the worker its topic names
(:func:`protocols.routing.worker_of`), and what one call took for a worker leaves as one message of
one frame, the msgpack array ``[topic, payload, topic, payload, ...]`` (each a ``bin``) that the
worker unpacks. A message that is not two frames goes as ``b"", b""`` (the worker refuses it as
undecodable), to the worker of its first frame. The same as the front's Python loop over
:func:`protocols.zeromq.receive` (tested against it), without a Python object per message but the
topic's ``bytes`` for the lookup: that loop cost the front about 7 µs a message, more than a worker
spends decoding it, and bounded one machine's streams whatever its cores.

The sockets are pyzmq's (``Socket.underlying``), the functions those of the libzmq pyzmq loaded
(addresses from :func:`protocols.zeromq.libzmq_functions`), called on the thread that owns the
sockets, as pyzmq would."""

from cpython.bytes cimport PyBytes_FromStringAndSize
from cpython.dict cimport PyDict_GetItem
from cpython.mem cimport PyMem_Free, PyMem_Malloc, PyMem_Realloc
from cpython.ref cimport PyObject
from libc.errno cimport EAGAIN, EINTR
from libc.stdint cimport uint32_t, uintptr_t
from libc.string cimport memcpy, memset


cdef extern from *:
    """
    /* libzmq's zmq_msg_t (zmq.h, stable since 4.0): 64 bytes, pointer-aligned */
    typedef struct { unsigned char _[64]; } __attribute__((aligned(sizeof(void *)))) mocapd_zmq_msg;
    """
    ctypedef struct mocapd_zmq_msg:
        pass

ctypedef int (*msg_init_f)(mocapd_zmq_msg *) noexcept nogil
ctypedef int (*msg_init_size_f)(mocapd_zmq_msg *, size_t) noexcept nogil
ctypedef int (*msg_io_f)(mocapd_zmq_msg *, void *, int) noexcept nogil
ctypedef int (*msg_close_f)(mocapd_zmq_msg *) noexcept nogil
ctypedef void *(*msg_data_f)(mocapd_zmq_msg *) noexcept nogil
ctypedef size_t (*msg_size_f)(const mocapd_zmq_msg *) noexcept nogil
ctypedef int (*msg_more_f)(const mocapd_zmq_msg *) noexcept nogil
ctypedef int (*errno_f)() noexcept nogil

FUNCTIONS = (
    "zmq_msg_init",
    "zmq_msg_init_size",
    "zmq_msg_recv",
    "zmq_msg_send",
    "zmq_msg_close",
    "zmq_msg_data",
    "zmq_msg_size",
    "zmq_msg_more",
    "zmq_errno",
)
"""The libzmq functions the router calls (their addresses are given by name)."""

cdef enum:
    DONTWAIT = 1  # ZMQ_DONTWAIT
    HEADER = 5  # a msgpack array32's tag and count
    ITEM = 5  # a msgpack bin32's tag and length


cdef struct Out:
    char *data
    Py_ssize_t size, capacity, count


cdef inline void put32(char *at, uint32_t value) noexcept nogil:
    at[0] = <char> (value >> 24)
    at[1] = <char> (value >> 16)
    at[2] = <char> (value >> 8)
    at[3] = <char> value


cdef class Router:
    """Routes the messages of the socket at ``source`` to the PUSH sockets at ``sinks`` (addresses,
    ``Socket.underlying``); ``functions``: name to address of each of :data:`FUNCTIONS`; ``choose``:
    a topic's worker (``bytes -> int`` in ``0 .. len(sinks) - 1``, or ``len(sinks)``: every
    worker, for a frame message), asked once per topic and
    remembered, at most ``cached`` topics (then forgotten all at once: a flood of new ids must
    not grow it)."""

    cdef msg_init_f init
    cdef msg_init_size_f init_size
    cdef msg_io_f recv
    cdef msg_io_f send
    cdef msg_close_f close
    cdef msg_data_f data
    cdef msg_size_f size
    cdef msg_more_f more
    cdef errno_f last_error
    cdef void *source
    cdef void **sinks
    cdef Out *out
    cdef readonly Py_ssize_t workers
    cdef dict routes
    cdef object choose
    cdef Py_ssize_t cached

    def __cinit__(self, dict functions, uintptr_t source, list sinks, choose, Py_ssize_t cached):
        missing = [name for name in FUNCTIONS if not functions.get(name)]
        if missing:
            raise ValueError(f"libzmq functions missing: {', '.join(missing)}")
        if not sinks:
            raise ValueError("no sockets to route to")
        self.init = <msg_init_f> <uintptr_t> functions["zmq_msg_init"]
        self.init_size = <msg_init_size_f> <uintptr_t> functions["zmq_msg_init_size"]
        self.recv = <msg_io_f> <uintptr_t> functions["zmq_msg_recv"]
        self.send = <msg_io_f> <uintptr_t> functions["zmq_msg_send"]
        self.close = <msg_close_f> <uintptr_t> functions["zmq_msg_close"]
        self.data = <msg_data_f> <uintptr_t> functions["zmq_msg_data"]
        self.size = <msg_size_f> <uintptr_t> functions["zmq_msg_size"]
        self.more = <msg_more_f> <uintptr_t> functions["zmq_msg_more"]
        self.last_error = <errno_f> <uintptr_t> functions["zmq_errno"]
        self.source = <void *> source
        self.workers = len(sinks)
        self.sinks = <void **> PyMem_Malloc(self.workers * sizeof(void *))
        self.out = <Out *> PyMem_Malloc(self.workers * sizeof(Out))
        if self.sinks == NULL or self.out == NULL:
            raise MemoryError()
        memset(self.out, 0, self.workers * sizeof(Out))
        for k in range(self.workers):
            self.sinks[k] = <void *> <uintptr_t> sinks[k]
        self.routes = {}
        self.choose = choose
        self.cached = max(1, cached)

    def __dealloc__(self):
        if self.out != NULL:
            for k in range(self.workers):
                PyMem_Free(self.out[k].data)
            PyMem_Free(self.out)
        PyMem_Free(self.sinks)

    cdef int worker(self, const char *topic, size_t length) except -1:
        key = PyBytes_FromStringAndSize(topic, length)
        cdef PyObject *found = PyDict_GetItem(self.routes, key)
        if found != NULL:
            return <object> found
        if len(self.routes) >= self.cached:
            self.routes.clear()
        k = self.choose(key)
        if not 0 <= k <= self.workers:  # ``workers``: to every worker
            raise ValueError(f"topic {key[:80]!r} routed to worker {k} of {self.workers}")
        self.routes[key] = k
        return k

    cdef int append(self, Py_ssize_t k, const char *a, size_t na, const char *b, size_t nb) except -1:
        cdef Out *o = &self.out[k]
        cdef Py_ssize_t need = (HEADER if o.count == 0 else 0) + 2 * ITEM + <Py_ssize_t> (na + nb)
        cdef Py_ssize_t capacity
        cdef char *grown
        if na > 0xFFFFFFFF or nb > 0xFFFFFFFF:
            raise ValueError("a frame of 4 GiB or more")
        if o.size + need > o.capacity:
            capacity = max(2 * o.capacity, o.size + need, 65536)
            grown = <char *> PyMem_Realloc(o.data, capacity)
            if grown == NULL:
                raise MemoryError()
            o.data, o.capacity = grown, capacity
        if o.count == 0:
            o.data[0] = <char> 0xDD
            o.size = HEADER
        o.data[o.size] = <char> 0xC6
        put32(&o.data[o.size + 1], <uint32_t> na)
        memcpy(&o.data[o.size + ITEM], a, na)
        o.size += ITEM + na
        o.data[o.size] = <char> 0xC6
        put32(&o.data[o.size + 1], <uint32_t> nb)
        memcpy(&o.data[o.size + ITEM], b, nb)
        o.size += ITEM + nb
        o.count += 1
        return 0

    cdef int fail(self) except -2:
        """-1 for a receive that found nothing (EAGAIN), 0 to try again (EINTR), else ZMQError."""
        cdef int e = self.last_error()
        if e == EAGAIN:
            return -1
        if e == EINTR:
            return 0
        import zmq

        raise zmq.ZMQError(e)

    def drain(self, Py_ssize_t most):
        """Route up to ``most`` messages that are waiting now; (the messages taken, per worker the
        messages that could not be sent: its queue was full)."""
        cdef mocapd_zmq_msg first, second
        cdef Py_ssize_t taken = 0, k, w
        cdef bint pair
        try:
            while taken < most:
                self.init(&first)
                if self.recv(&first, self.source, DONTWAIT) < 0:
                    self.close(&first)
                    if self.fail() < 0:
                        break
                    continue
                self.init(&second)
                try:
                    pair = False
                    if self.more(&first):
                        self.next(&second)
                        pair = not self.more(&second)
                        while self.more(&second):  # three frames or more: the rest read and dropped
                            self.close(&second)
                            self.init(&second)
                            self.next(&second)
                    k = self.worker(<const char *> self.data(&first), self.size(&first))
                    for w in range(self.workers) if k == self.workers else range(k, k + 1):
                        if pair:
                            self.append(
                                w,
                                <const char *> self.data(&first),
                                self.size(&first),
                                <const char *> self.data(&second),
                                self.size(&second),
                            )
                        else:
                            self.append(w, NULL, 0, NULL, 0)
                finally:
                    self.close(&first)
                    self.close(&second)
                taken += 1
        finally:
            full = self.flush()
        return taken, full

    cdef int next(self, mocapd_zmq_msg *frame) except -1:
        """The next frame of a multipart message, which arrives whole: it is there already."""
        while self.recv(frame, self.source, DONTWAIT) < 0:
            if self.fail() < 0:
                raise RuntimeError("a multipart message arrived in part")
        return 0

    cdef list flush(self):
        cdef list full = [0] * self.workers
        cdef mocapd_zmq_msg frame
        cdef Out *o
        cdef Py_ssize_t k
        for k in range(self.workers):
            o = &self.out[k]
            if o.count == 0:
                continue
            put32(&o.data[1], <uint32_t> (2 * o.count))  # a topic and a payload each
            if self.init_size(&frame, o.size) == 0:
                memcpy(self.data(&frame), o.data, o.size)
                while self.send(&frame, self.sinks[k], DONTWAIT) < 0:
                    if self.last_error() != EINTR:
                        full[k] = o.count
                        self.close(&frame)
                        break
            else:
                full[k] = o.count
            o.size = o.count = 0
        return full
