/*
 * interp.c - what the clone core reads and mends of CPython's interpreter
 * state: the garbage collector's lists and counts, and the free lists.
 *
 * 1. No node process ever runs a collection.
 * A collection in progress splits the generations into lists on the
 * collecting thread's stack and keeps each object's reference count in its
 * list link (gcmodule.c: update_refs .. move_unreachable).  A node process
 * killed in there left those links so, and gcstate->collecting at 1 (no
 * collection ever ran again); the next untrack anywhere followed a count
 * as a pointer and the container died (bench.random_kill).  So in isolated
 * mode automatic collection is off and a thread of the container collects
 * (collector.py), when CPython itself would have: cg_gc_wait_due tells it,
 * waiting without the GIL.
 *
 * Built with Py_BUILD_CORE against the internal headers of the interpreter
 * the extension is compiled for (3.11.7, like gilrepair.c; assumptions.py
 * checks that the running one is that one).
 */
#define Py_BUILD_CORE 1
#include <Python.h>
#include "internal/pycore_interp.h" /* PyInterpreterState.gc, free lists */
#include "internal/pycore_frame.h"  /* _PyInterpreterFrame (a dead task's locals) */
#include "internal/pycore_object.h" /* _PyObject_GC_IS_TRACKED */

#include <errno.h>
#include <stdbool.h>
#include <stdint.h>
#include <sys/uio.h>
#include <time.h>
#include <unistd.h>

#include "repair.h"

#define NEXT(g) ((PyGC_Head *)(g)->_gc_next)
#define PREV(g) ((PyGC_Head *)((g)->_gc_prev & _PyGC_PREV_MASK))
#define WALK_LIMIT (1L << 30) /* more than any heap holds: a cycle guard */

static PyInterpreterState *interp(void)
{
    return PyInterpreterState_Main();
}

static void set_prev(PyGC_Head *g, PyGC_Head *p)
{
    g->_gc_prev = (g->_gc_prev & ~_PyGC_PREV_MASK) | (uintptr_t)p;
}

/* The generation CPython 3.11 would collect now (gc_collect_generations:
   the oldest whose count is over its threshold, the oldest only once a
   quarter of the long-lived objects are new), ignoring `enabled`; -1 if
   none, or if thresholds are off (threshold 0). */
static int due(const struct _gc_runtime_state *g)
{
    if (g->generations[0].threshold == 0 || g->generations[0].count <= g->generations[0].threshold)
        return -1;
    for (int i = NUM_GENERATIONS - 1; i >= 0; i--) {
        if (g->generations[i].count <= g->generations[i].threshold)
            continue;
        if (i == NUM_GENERATIONS - 1 && g->long_lived_pending < g->long_lived_total / 4)
            continue;
        return i;
    }
    return -1;
}

/* Wait (no GIL needed: the counts are plain ints, read racily, and only
   decide when to look again) until a collection is due or *wake is set,
   looking every interval_us.  The generation to collect, or -1 if woken. */
int cg_gc_wait_due(int interval_us, int *wake)
{
    const struct _gc_runtime_state *g = &PyInterpreterState_Main()->gc;
    struct timespec ts = {interval_us / 1000000, (long)(interval_us % 1000000) * 1000};
    for (;;) {
        if (__atomic_load_n(wake, __ATOMIC_ACQUIRE))
            return -1;
        int gen = due(g);
        if (gen >= 0)
            return gen;
        while (nanosleep(&ts, NULL) < 0 && errno == EINTR) {
        }
    }
}

/* ---------------------------------------------------------------------- */
/* 2. After a death with the GIL held.
 *
 * A node process killed while it ran Python can leave what it was doing
 * half-done, and the GIL repair then lets everyone else in.  Most of what it
 * can leave half-done is objects it was building or changing (a list whose
 * size grew before its new item was stored): harmless to everyone but the
 * garbage collector, which traverses every tracked object and would follow
 * the garbage.  So, while the GIL is still the dead task's (nobody runs
 * Python), the collector is made never to look at them again (a cycle
 * through one is never freed: a bounded leak, like the rest of a dead node):
 *
 *   young objects  the young generation (everything tracked since the last
 *                  collection: the dead node's new lists, whichever free
 *                  list they came from) moves to the permanent generation,
 *                  which no collection traverses (gc.freeze()'s);
 *   its frames'    every tracked object a local variable of its frames
 *   locals         refers to (and a cell's content) is untracked: an old
 *                  list it was appending to;
 *   its pools      its Python object pools are abandoned (pyalloc.c), and
 *                  every tracked object in an abandoned pool is untracked
 *                  before the next collection of its generation (below).
 *
 * and what it may have left half-linked is mended:
 *
 *   GC links       tracking and untracking are four plain stores each (the
 *                  young generation's tail, or an object's neighbours): the
 *                  young generation is walked and every prev link made to
 *                  agree with the next links; a track stopped half-way at
 *                  the tail is completed;
 *   free lists     a push is a store and a count: both emptied (what was in
 *                  them is leaked, never handed out twice).
 *
 * What stays a measured risk (docs/evidence.md): an object the dead node
 * shared with others (a module's dict, a list another node reads), or one
 * it reached only through another object's attribute and that came from a
 * free list, left half-changed.
 */

static _Atomic long g_epoch;                 /* pool abandonments so far */
static long g_untracked_at[NUM_GENERATIONS]; /* g_epoch when last walked */

/* Make every prev link of list h agree with its next links (a next link of
   0, a track stopped half-way, ends the list there; a tail the head's prev
   names, whose own links point back at the list's end, is linked in), and
   untrack every object for which drop(gc) holds.  The count of links
   mended. */
static long walk(PyGC_Head *h, int (*drop)(const void *), long *dropped)
{
    long mended = 0, steps = 0;
    PyGC_Head *prev = h, *cur = NEXT(h);
    while (cur != h && steps++ < WALK_LIMIT) {
        if (cur == NULL) { /* h's own next was 0 */
            prev->_gc_next = (uintptr_t)h;
            mended++;
            break;
        }
        if (PREV(cur) != prev) {
            set_prev(cur, prev);
            mended++;
        }
        PyGC_Head *next = NEXT(cur);
        if (next == NULL) { /* the tail of a half-done track */
            cur->_gc_next = (uintptr_t)h;
            next = h;
            mended++;
        }
        if (drop && drop(cur)) {
            prev->_gc_next = (uintptr_t)next; /* next's prev: its own turn, or below */
            cur->_gc_next = 0;
            cur->_gc_prev &= _PyGC_PREV_MASK_FINALIZED;
            (*dropped)++;
        } else {
            prev = cur;
        }
        cur = next;
    }
    PyGC_Head *claimed = PREV(h);
    if (claimed != prev) {
        if (claimed && claimed != h && PREV(claimed) == prev &&
            (NEXT(claimed) == h || NEXT(claimed) == NULL)) {
            prev->_gc_next = (uintptr_t)claimed; /* a half-done track: finish it */
            claimed->_gc_next = (uintptr_t)h;
            prev = claimed;
        }
        set_prev(h, prev);
        mended++;
    }
    return mended;
}

static int empty_free_lists(PyInterpreterState *in)
{
    int any = 0;
#define EMPTY(count, head)                                                                         \
    do {                                                                                           \
        any |= (count) != 0;                                                                       \
        (count) = 0;                                                                               \
        (head) = NULL;                                                                             \
    } while (0)
    EMPTY(in->float_state.numfree, in->float_state.free_list);
    for (int i = 0; i < PyTuple_NFREELISTS; i++)
        EMPTY(in->tuple.numfree[i], in->tuple.free_list[i]);
    EMPTY(in->list.numfree, in->list.free_list[0]);
    EMPTY(in->dict_state.numfree, in->dict_state.free_list[0]);
    EMPTY(in->dict_state.keys_numfree, in->dict_state.keys_free_list[0]);
    EMPTY(in->async_gen.value_numfree, in->async_gen.value_freelist[0]);
    EMPTY(in->async_gen.asend_numfree, in->async_gen.asend_freelist[0]);
    EMPTY(in->context.numfree, in->context.freelist);
    EMPTY(in->exc_state.memerrors_numfree, in->exc_state.memerrors_freelist);
#undef EMPTY
    any |= in->slice_cache != NULL;
    in->slice_cache = NULL;
    return any;
}

/* Unlink gc from whatever list holds it, if its neighbours agree that
   they are its neighbours (else leave it: never write through a link that
   is not one). */
static int untrack(PyGC_Head *gc)
{
    PyGC_Head *prev = PREV(gc), *next = NEXT(gc);
    if (!next || !prev || NEXT(prev) != gc || PREV(next) != gc)
        return 0;
    prev->_gc_next = (uintptr_t)next;
    set_prev(next, prev);
    gc->_gc_next = 0;
    gc->_gc_prev &= _PyGC_PREV_MASK_FINALIZED;
    return 1;
}

/* What a dead task left is read only through cg_peek: process_vm_readv on
   this process fails with EFAULT where a load would fault.  A task killed
   while it pushed or cleared a frame leaves locals that point at freed or
   never-written memory (0x23, 0x200000221: deep-15-outside, where the
   monitor itself died of them), and this runs on the monitor. */
bool cg_peek(const void *addr, void *out, size_t len)
{
    struct iovec here = {out, len}, there = {(void *)addr, len};
    return process_vm_readv(getpid(), &here, 1, &there, 1, 0) == (ssize_t)len;
}

/* Could p be an object's (or a frame's, a code object's, a type's)
   address?  Words read from a dead thread's frames are not trusted: one
   seen there was 0x23.  Only an aligned pointer is followed, so that no
   member of a misaligned one is even named (undefined behaviour in C,
   which UBSan reports, before cg_peek would refuse to read it). */
static bool aligned(const void *p)
{
    return p && ((uintptr_t)p & (_Alignof(PyObject) - 1)) == 0;
}

/* op, if it is a tracked GC object whose list neighbours agree, unlinked.
   An object here has a type whose own type is a type, with HAVE_GC and no
   tp_is_gc (never call code found through memory not yet trusted). */
static int untrack_object(PyObject *op)
{
    PyTypeObject *type, *meta;
    unsigned long flags, meta_flags;
    inquiry is_gc;
    if (!aligned(op) || !PEEK(&op->ob_type, type) || !aligned(type) ||
        !PEEK(&type->ob_base.ob_base.ob_type, meta) || !aligned(meta) ||
        !PEEK(&meta->tp_flags, meta_flags) || !(meta_flags & Py_TPFLAGS_TYPE_SUBCLASS) ||
        !PEEK(&type->tp_flags, flags) || !(flags & Py_TPFLAGS_HAVE_GC) ||
        !PEEK(&type->tp_is_gc, is_gc) || is_gc)
        return 0;
    PyGC_Head *gc = _Py_AS_GC(op), head, prev_head, next_head;
    if (!PEEK(gc, head) || !head._gc_next)
        return 0; /* unreadable, or not tracked */
    PyGC_Head *prev = PREV(&head), *next = NEXT(&head);
    if (!prev || !PEEK(prev, prev_head) || !PEEK(next, next_head))
        return 0;
    return untrack(gc); /* reads and writes only what was read */
}

/* The dead thread state's frames (3.11: tstate->cframe->current_frame,
   then previous): every local (a live reference or NULL in a frame that
   is whole; the value stack of the frame that was running is not known,
   and not read) and every cell's content. */
static long untrack_locals(PyThreadState *t)
{
    long n = 0, frames = 0;
    _PyCFrame *cframe;
    _PyInterpreterFrame *f;
    if (!t || !PEEK(&t->cframe, cframe) || !aligned(cframe) || !PEEK(&cframe->current_frame, f))
        return 0;
    for (; aligned(f) && frames < 10000; frames++) {
        PyCodeObject *code;
        PyTypeObject *code_type;
        int count;
        if (!PEEK(&f->f_code, code) || !aligned(code) ||
            !PEEK(&code->ob_base.ob_base.ob_type, code_type) || code_type != &PyCode_Type ||
            !PEEK(&code->co_nlocalsplus, count) || count < 0 || count > (1 << 16))
            break;
        for (int i = 0; i < count; i++) {
            PyObject *op, *content;
            PyTypeObject *type;
            if (!PEEK(&f->localsplus[i], op))
                break;
            if (aligned(op) && PEEK(&op->ob_type, type) && type == &PyCell_Type &&
                PEEK(&((PyCellObject *)op)->ob_ref, content))
                n += untrack_object(content);
            n += untrack_object(op);
        }
        if (!PEEK(&f->previous, f))
            break;
    }
    return n;
}

/* ---------------------------------------------------------------------- */
/* 3. What a dead task's frames still refer to (reclaim.py gives back what
   only a dead node could reach, counting references: a reference it may
   count must be one for certain).  Read through cg_peek, with the GIL
   held by the caller's thread (taken here), long after the death.

   known    words that are references for certain, each once per reference:
            in a frame below the innermost one (past its set-up: it is
            suspended in a call, so it is whole), its function, code, locals
            dict and frame object, and its locals; its value stack up to
            stacktop where the call saved it (an inlined Python call does),
            else not known.  In the innermost frame, running and whole
            (stacktop -1: 3.11 saves it only to return, trace or call
            Python), its locals (STORE_FAST writes a local before it drops
            the old value, so the slot always holds one).  A generator's
            frame (running: its stacktop is -1) counts its locals only.
   unknown  the innermost frame's other words, what its last instruction
            may have been changing: all of them if it is being set up or
            torn down (stacktop saved), its function, code, locals dict and
            frame object else.  Of the frames below, what is not known is
            not read: the value stacks of frames that called C, what a
            generator's traversal counts, any stack past a saved stacktop
            (stale).  Whatever an outer frame's call was working on is
            whole: C code that calls Python code leaves what it works on
            whole, since that code may look at it.
   stack    the running innermost frame's value stack, every word of it
            (top: its code object's address, its instruction's offset in
            code units, how many words): how deep it stands, and so which
            words are references, only its bytecode tells (reclaim.py).
            top[0] is 0 if the innermost frame is not running and whole
            (its words are then unknown).
   Returns 0 (counts[0], counts[1]: how many known and unknown), -ENOSPC if
   an array was too small (then nothing may be counted), -EINVAL if no frame
   could be read. */
struct refs {
    uintptr_t *w;
    int n, max;
};

/* The running innermost frame's place and value stack. */
struct top {
    uintptr_t *where; /* code, offset, words */
    struct refs stack;
};

static bool put(struct refs *r, const void *p)
{
    if (!p || !r) /* no r: a word nobody needs */
        return true;
    if (r->n >= r->max)
        return false;
    r->w[r->n++] = (uintptr_t)p;
    return true;
}

/* localsplus[from, to) of f, each word into r. */
static bool put_slots(struct refs *r, _PyInterpreterFrame *f, int from, int to)
{
    for (int i = from; i < to; i++) {
        PyObject *op;
        if (!PEEK(&f->localsplus[i], op) || !put(r, op))
            return false;
    }
    return true;
}

static bool frame_refs(_PyInterpreterFrame *f, struct top *innermost, struct refs *known,
                       struct refs *unknown)
{
    struct {
        PyCodeObject *code;
        PyFunctionObject *func;
        PyObject *locals;
        PyFrameObject *obj;
        _Py_CODEUNIT *prev_instr;
        int stacktop;
        char owner;
    } h;
    int nlocals, stacksize, first;
    PyTypeObject *code_type;
    if (!PEEK(&f->f_code, h.code) || !aligned(h.code) ||
        !PEEK(&h.code->ob_base.ob_base.ob_type, code_type) || code_type != &PyCode_Type ||
        !PEEK(&h.code->co_nlocalsplus, nlocals) || !PEEK(&h.code->co_stacksize, stacksize) ||
        !PEEK(&h.code->_co_firsttraceable, first) || nlocals < 0 || stacksize < 0 ||
        nlocals + stacksize > (1 << 16) || !PEEK(&f->f_func, h.func) ||
        !PEEK(&f->f_locals, h.locals) || !PEEK(&f->frame_obj, h.obj) ||
        !PEEK(&f->prev_instr, h.prev_instr) || !PEEK(&f->stacktop, h.stacktop) ||
        !PEEK(&f->owner, h.owner))
        return false;
    int top = nlocals + stacksize;
    /* A generator's frame is whole once made.  Its generator's traversal
       (_PyFrame_Traverse) counts its function, code, locals dict and frame
       object always, and its locals and stack up to a saved stacktop: the
       walk never counts those again. */
    bool gen = h.owner == FRAME_OWNED_BY_GENERATOR;
    bool whole =
        gen || (h.owner == FRAME_OWNED_BY_THREAD && h.prev_instr >= _PyCode_CODE(h.code) + first);
    bool saved = h.stacktop >= nlocals && h.stacktop <= top;
    if (!whole || (innermost && h.stacktop != -1) ||
        (gen && saved)) /* set up, torn down, or counted */
        return put(unknown, h.code) && put(unknown, h.func) && put(unknown, h.locals) &&
               put(unknown, h.obj) && put_slots(unknown, f, 0, top);
    struct refs *specials_to = innermost || gen ? unknown : known;
    if (!put(specials_to, h.code) || !put(specials_to, h.func) || !put(specials_to, h.locals) ||
        !put(specials_to, h.obj))
        return false;
    if (innermost) { /* running */
        for (int i = nlocals; i < top;
             i++) { /* every word, NULL too: the bytecode says which count */
            PyObject *op;
            if (!PEEK(&f->localsplus[i], op) || innermost->stack.n >= innermost->stack.max)
                return false;
            innermost->stack.w[innermost->stack.n++] = (uintptr_t)op;
        }
        innermost->where[0] = (uintptr_t)h.code;
        innermost->where[1] = (uintptr_t)(h.prev_instr - _PyCode_CODE(h.code));
        innermost->where[2] = (uintptr_t)innermost->stack.n;
        return put_slots(known, f, 0, nlocals);
    }
    if (saved) /* suspended in an inlined call: saved */
        return put_slots(known, f, 0, h.stacktop);
    return put_slots(known, f, 0, nlocals) && put_slots(unknown, f, nlocals, top);
}

int cg_dead_frame_refs(void *tstate, uintptr_t *known, int nknown, uintptr_t *unknown, int nunknown,
                       uintptr_t *stack, int nstack, uintptr_t *top, int *counts)
{
    PyThreadState *t = tstate;
    struct refs k = {known, 0, nknown}, u = {unknown, 0, nunknown};
    struct top running = {top, {stack, 0, nstack}};
    top[0] = top[1] = top[2] = 0;
    _PyCFrame *cframe;
    _PyInterpreterFrame *f;
    int rc = 0, frames = 0;
    PyGILState_STATE gs = PyGILState_Ensure();
    if (!t || !PEEK(&t->cframe, cframe) || !aligned(cframe) || !PEEK(&cframe->current_frame, f))
        rc = -EINVAL;
    for (; rc == 0 && f && frames < 10000; frames++) {
        if (!aligned(f) ||
            !frame_refs(f, frames == 0 ? &running : NULL, &k, frames == 0 ? &u : NULL))
            rc = k.n >= k.max || u.n >= u.max || running.stack.n >= running.stack.max ? -ENOSPC
                                                                                      : -EINVAL;
        else if (!PEEK(&f->previous, f))
            rc = -EINVAL;
    }
    PyGILState_Release(gs);
    counts[0] = k.n;
    counts[1] = u.n;
    return rc;
}

/* gc_list_merge(from, to), gcmodule.c's: every object of from, at the end
   of to. */
static void merge(PyGC_Head *from, PyGC_Head *to)
{
    if (NEXT(from) == from)
        return;
    PyGC_Head *tail = PREV(to), *first = NEXT(from), *last = PREV(from);
    tail->_gc_next = (uintptr_t)first;
    set_prev(first, tail);
    last->_gc_next = (uintptr_t)to;
    set_prev(to, last);
    from->_gc_next = (uintptr_t)from;
    from->_gc_prev = (uintptr_t)from;
}

uint32_t cg_interp_after_gil_death(int slot, PyThreadState *dead)
{
    PyInterpreterState *in = interp();
    uint32_t done = 0;
    if (slot > 0 && guard_py_abandon(slot) == 0) {
        __atomic_fetch_add(&g_epoch, 1, __ATOMIC_RELEASE);
        done |= CG_REPAIR_PY_POOLS;
    }
    long none = 0;
    PyGC_Head *young = &in->gc.generations[0].head;
    if (walk(young, NULL, &none))
        done |= CG_REPAIR_GC_LINKS;
    if (untrack_locals(dead))
        done |= CG_REPAIR_PY_OBJECTS;
    if (NEXT(young) != young) {
        merge(young, &in->gc.permanent_generation.head);
        done |= CG_REPAIR_PY_OBJECTS;
    }
    if (empty_free_lists(in))
        done |= CG_REPAIR_FREELISTS;
    return done;
}

/* The collector's thread, about to collect `generation` (with the GIL,
   taken here): untrack, in that generation and every younger one, the
   objects of pools abandoned since each was last walked (and mend any link
   on the way); then collect, with `collect` (gc.collect, a borrowed
   reference), in the same hold of the GIL.  What collect returned, or -1
   (its exception printed). */
long cg_gc_collect(void *collect, int generation)
{
    PyGILState_STATE gs = PyGILState_Ensure();
    PyInterpreterState *in = interp();
    long epoch = __atomic_load_n(&g_epoch, __ATOMIC_ACQUIRE);
    for (int g = 0; g <= generation && g < NUM_GENERATIONS; g++) {
        if (g_untracked_at[g] == epoch)
            continue;
        long dropped = 0;
        walk(&in->gc.generations[g].head, guard_py_abandoned, &dropped);
        g_untracked_at[g] = epoch;
    }
    long n = -1;
    PyObject *r = PyObject_CallFunction((PyObject *)collect, "i", generation);
    if (r) {
        n = PyLong_AsLong(r);
        Py_DECREF(r);
    }
    if (PyErr_Occurred())
        PyErr_Print();
    PyGILState_Release(gs);
    return n;
}

/* ---------------------------------------------------------------------- */
/* For assumptions.py (takes the GIL itself): the compiled view of the
   collector's state and the free lists against the running interpreter. */
int cg_interp_probe(struct cg_interp_probe *out)
{
    PyGILState_STATE gs = PyGILState_Ensure();
    PyInterpreterState *in = interp();
    struct _gc_runtime_state *g = &in->gc;
    for (int i = 0; i < 3; i++) {
        out->threshold[i] = g->generations[i].threshold;
        out->count[i] = g->generations[i].count;
    }
    out->generation0_is_head = g->generation0 == &g->generations[0].head;
    out->enabled = g->enabled;
    out->collecting = g->collecting;
    /* The young generation, both ways: as long, and every link agreeing. */
    long fwd = 0, consistent = 1;
    PyGC_Head *h = &g->generations[0].head;
    for (PyGC_Head *c = NEXT(h), *p = h; c != h && fwd < WALK_LIMIT; p = c, c = NEXT(c), fwd++)
        if (!c || PREV(c) != p) {
            consistent = 0;
            break;
        }
    long back = 0;
    for (PyGC_Head *c = PREV(h); c && c != h && back < WALK_LIMIT; c = PREV(c))
        back++;
    out->young_links_ok = consistent && fwd == back;
    out->free_lists_ok =
        in->float_state.numfree >= 0 && in->float_state.numfree <= PyFloat_MAXFREELIST &&
        in->list.numfree >= 0 && in->list.numfree <= PyList_MAXFREELIST &&
        in->dict_state.numfree >= 0 && in->dict_state.numfree <= PyDict_MAXFREELIST &&
        in->dict_state.keys_numfree >= 0 && in->dict_state.keys_numfree <= PyDict_MAXFREELIST;
    PyGILState_Release(gs);
    return 0;
}
