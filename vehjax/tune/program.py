"""The compiled program of a fit: the loss, its gradient and (forward mode) the per-step scores
on a flat vector of coordinates, compiled once and used by every part of the fit (optimiser,
line search, curvature, Newton polish).

Forward mode (:func:`forward_scores`) for a deterministic filter with at most
:data:`FORWARD_MAX` coordinates: n tangents carried through the filter beside the state, every
step's score, nothing stored for a backward pass; for a few coordinates and long runs several
times cheaper than reverse mode through the scan. Reverse mode (``jax.value_and_grad``)
beyond, and for particle filters. Measurements: ``benchmarks/results/notes_tune.md``.

A forward-mode program takes its directions as an argument, a block of them per call
(:func:`vehjax.execution.direction_block`): on a machine with cores to spare a point is
evaluated in blocks at once on several threads, each repeating the filter's own arithmetic,
and the blocks joined (:func:`joined`: the gradient's entries in turn, the BHHH matrix's
between blocks from the per-step scores). The loss is the same to the bit whatever the blocks;
the gradient and the BHHH matrix to rounding.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, NamedTuple

import jax
import jax.flatten_util
import jax.numpy as jnp
import numpy as np

from .. import execution
from . import priors as tune_priors

__all__ = ["CompiledLoss", "Program", "Layout", "serves", "compile_directed", "forward_scores",
           "score_outer_product", "compile_program", "compiled_loss", "prior_terms",
           "FORWARD_MAX", "batched_hessian", "joined", "at_once"]

#: forward-mode derivatives (:func:`forward_scores`) for at most this many coordinates; reverse
#: mode beyond (its cost does not grow with the number of coordinates)
FORWARD_MAX = 12


def batched_hessian(n_steps: int) -> bool:
    """Whether a forward-mode fit of ``n_steps`` run-steps (R T) with a Hessian by differences
    computes the Hessian's 2 n gradients in one program vmapped over the points
    (:func:`compiled_loss`'s ``batch_hessian``): the platform's rule, ``batched_hessian_steps``
    of :mod:`vehjax.execution` (never on the CPU)."""
    at = execution.current().batched_hessian_steps
    return at is not None and n_steps >= at


class CompiledLoss(NamedTuple):
    """The loss on a flat vector of coordinates (``ravel_pytree`` of z): ``vg(f) -> (loss,
    aux, grad)`` compiled once per fit and used by every part of it. ``vgo(f) -> (loss, aux,
    grad, opg)`` (forward mode only, else None) also gives the outer product of the per-step
    scores (:func:`score_outer_product`) from the same evaluation. ``grads(F) -> (k, n)``: the
    gradients at the k = 2 n points F (k, n) of the Hessian's central differences
    (:func:`vehjax.tune.hessian_from_gradients`) in one vmapped forward-mode program, or None
    (:func:`batched_hessian`). ``many(points) -> [vg(p) for p in points]``, the points (each
    in its blocks of directions, :class:`Program`) evaluated side by side on
    :mod:`vehjax.execution`'s ``side_by_side`` host threads (one evaluation of a filter's scan
    keeps about one CPU core busy); ``vg`` and ``vgo`` a point's blocks on the threads not
    taken by work in flight beside (:func:`vehjax.execution.spare_threads`). ``stats``: ``mode``
    ("forward" or "reverse"), ``compile_seconds``, ``evaluations`` (of vg/vgo; a repeated
    point is not evaluated again), ``batch_compile_seconds`` and ``batch_evaluations`` (of
    grads)."""

    vg: Callable
    unravel: Callable
    x0: np.ndarray
    vgo: Callable | None = None
    stats: dict | None = None
    grads: Callable | None = None
    many: Callable | None = None


def forward_scores(per_step, f, data, directions=None):
    """Per-step log-likelihoods and their derivatives by forward mode.

    ``m`` Jacobian-vector products of ``per_step`` along ``directions`` (m, n) (None: the n
    coordinate axes), vmapped: one pass through the filter carrying m tangents beside the
    state, nothing stored for a backward pass. For a few coordinates and long runs this is
    several times cheaper than reverse mode through the scan
    (``benchmarks/results/notes_tune.md``), and it gives every step's score, not only their
    sum.

    Args:
        per_step: ``per_step(f, data) -> (loglik (R, T), aux)``, f (n,) flat coordinates.
        f: (n,) point; data: the objective's data, ``(ys, us, x0, P0, keys)``.
        directions: (m, n) tangent directions, or None (the identity).

    Returns:
        (loglik (R, T), d loglik / df along each direction (m, R, T), aux).
    """
    basis = jnp.eye(f.shape[0], dtype=f.dtype) if directions is None else directions
    m = basis.shape[0]
    x0, P0 = data[2], data[3]
    # the prior's tangents explicit zeros, one per direction: the filter's carried state then
    # has non-zero, batched tangents from its first step, and JAX traces the scan's body once
    # for the tangents and once for the directions instead of iterating to a fixed point
    # (the brush fit's program: one jvp and one batching pass fewer; the values are the same)
    zx, zP = jnp.zeros((m,) + x0.shape, x0.dtype), jnp.zeros((m,) + P0.shape, P0.dtype)

    def jvp(v, dx, dP):
        return jax.jvp(lambda g, a, b: per_step(g, (*data[:2], a, b, *data[4:])),
                       (f, x0, P0), (v, dx, dP), has_aux=True)

    return jax.vmap(jvp, out_axes=(None, 0, None))(basis, zx, zP)


def score_outer_product(scores, n_steps: int):
    """The BHHH matrix (Berndt, Hall, Hall & Hausman 1974): ``sum_t s_t s_t^T / n_steps`` of
    the per-step scores ``s_t = d log p(y_t | y_1:t-1) / dz`` (``scores`` (n, ...) with the
    steps in the trailing axes), (n, n). At the true parameters it has the expectation of the
    Hessian of the mean negative log-likelihood per step (the information identity), so it
    is a positive semi-definite Gauss-Newton-type curvature from first derivatives only."""
    s = scores.reshape(scores.shape[0], -1)
    return (s @ s.T) / n_steps


def prior_terms(log_prior, unravel, f, n_steps: int, curvature: bool = True):
    """(value, gradient (n,), curvature (n, n) or None) of the prior's penalty on the loss at
    the flat coordinates f: minus the log prior (``log_prior(z)``, :mod:`vehjax.tune.priors`)
    over ``n_steps``, its gradient (reverse mode: a few scalar operations, nothing of the
    filter) and its Hessian floored to a positive semi-definite diagonal
    (:func:`vehjax.tune.priors.prior_curvature`), the term the BHHH matrix of the penalised
    loss gets; zeros when ``log_prior`` is None."""
    if log_prior is None:
        return 0.0, jnp.zeros_like(f), (jnp.zeros((f.shape[0],) * 2, f.dtype) if curvature
                                          else None)
    fn = lambda g: log_prior(unravel(g))  # noqa: E731
    v, g = jax.value_and_grad(fn)(f)
    H = tune_priors.prior_curvature(jax.hessian(fn)(f)) / n_steps if curvature else None
    return -v / n_steps, -g / n_steps, H


def _penalised(ll, dll, lls_div, prior, n_steps: int):
    """(loss, aux, grad, BHHH matrix or None) of a forward-mode evaluation: the per-step
    log-likelihoods ``ll`` (R, T) and their derivatives ``dll`` (m, R, T) along m directions,
    the prior's terms ``prior`` = (value, gradient (m,), curvature (m, m) or None) along the
    same directions (:func:`prior_terms`); the loss and its gradient the mean negative
    log-likelihood per run-step plus the prior's penalty, the BHHH matrix
    (:func:`score_outer_product`) plus its curvature."""
    pv, pg, pH = prior
    grad = -jnp.sum(dll.reshape(dll.shape[0], -1), axis=1) / n_steps + pg
    B = None if pH is None else score_outer_product(dll, n_steps) + pH
    return -jnp.sum(ll) / n_steps + pv, (jnp.sum(ll, axis=-1), lls_div), grad, B


def _reverse(obj, unravel):
    """The reverse-mode program: ``(f, data) -> (loss, aux, grad, None)`` by
    ``jax.value_and_grad`` of the objective's (penalised) loss."""
    vgf = jax.value_and_grad(lambda f, data: obj.loss(unravel(f), data), has_aux=True)

    def program(f, data):
        (v, aux), g = vgf(f, data)
        return v, aux, g, None

    return program


class Layout(NamedTuple):
    """How a fit's coordinates sit among those of a program over more
    (:func:`compile_directed`): its score tests' objective, the fit's coordinates and the
    held parameters ``extra`` (N in all).

    Attributes:
        extra: the held parameters' names, in the program's order.
        fit_names: the fit's coordinates' names (n,), in its flat order.
        fit_pos: their positions among the program's N coordinates (n,).
        held_pos: the held parameters' positions among them (k,).
        anchor: the held parameters' coordinates at their held values (k,): the program
            reads them relative to these (:func:`vehjax.tune.likelihood.anchored_physical`).
        held: their held values (k,), physical units: the program's constants.
        size: N.
    """

    extra: tuple
    fit_names: tuple
    fit_pos: np.ndarray
    held_pos: np.ndarray
    anchor: np.ndarray
    held: np.ndarray
    size: int


def serves(layout: Layout | None, fit_names, model) -> bool:
    """Whether a program with ``layout`` serves a fit of coordinates ``fit_names`` of
    ``model`` (its held parameters at the program's values)."""
    if layout is None:
        return False
    theta = np.asarray(model.theta, dtype=float)
    held = [theta[list(model.param_names).index(p)] for p in layout.extra]
    return tuple(fit_names) == layout.fit_names and np.array_equal(held, layout.held)


def _forward(obj, setup, unravel, anchored: bool = False):
    """The forward-mode program: ``(f (N,), V (m, N), anchor (k,), data) -> (loss, aux, V grad,
    V B V^T, scores (m, R T))`` of the objective ``obj`` along the m directions V: the loss,
    gradient and BHHH matrix penalised by its priors (:func:`prior_terms`, :func:`_penalised`)
    and the per-step scores. ``anchored``: the set-up ``setup`` reads its held parameters
    relative to ``anchor`` (:func:`vehjax.tune.likelihood.prepare_fit`); else ``anchor`` is
    empty and unused."""
    per_step, log_prior = setup.per_step, setup.log_prior

    def program(f, V, anchor, data):
        at = (lambda g: {**unravel(g), "anchor": anchor}) if anchored else unravel  # noqa: E731
        ll, dll, lls_div = forward_scores(lambda g, d: per_step(at(g), d), f, data, V)
        pv, pg, pH = prior_terms(log_prior, at, f, obj.n_steps)
        return (*_penalised(ll, dll, lls_div, (pv, V @ pg, V @ pH @ V.T), obj.n_steps),
                dll.reshape(V.shape[0], -1))

    return program


class Program(NamedTuple):
    """A fit's program compiled (:func:`compile_program`) on the flat coordinates f. The
    fitted values are its argument, so one program serves every start of the same objective
    (:func:`vehjax.tune.fit` compiles the next stage's program while the nested model is
    fitted); ``stats`` the compile's.

    Reverse mode: ``compiled(f, data) -> (loss, aux, grad, None)``. Forward mode
    (:func:`_forward`): ``compiled(f (N,), V (block, N), anchor (k,), data) -> (loss, aux, V
    grad, V BHHH V^T, the per-step scores along V (block, R T))``, ``block`` directions a call
    (:func:`vehjax.execution.direction_block`): :func:`compiled_loss` evaluates a point a block
    at a time, the blocks at once on :mod:`vehjax.execution`'s ``side_by_side`` threads. With
    a ``layout`` (:func:`compile_directed`) the program is that of the fit's score tests, over
    the fit's coordinates and the held parameters': it serves the fit (V rows of its
    coordinates, the held ones at their anchor) and the tests' full gradient."""

    compiled: Callable
    forward: bool
    options: dict | None
    stats: dict
    layout: Layout | None = None
    block: int | None = None


def _compiled(fn, args, options):
    """(``jax.jit(fn)`` lowered at ``args`` and compiled ahead of time with the XLA
    ``options``, the compile's wall and CPU seconds)."""
    t0, c0 = time.perf_counter(), time.process_time()
    compiled = jax.jit(fn).lower(*args).compile(compiler_options=options)
    return compiled, {"compile_seconds": time.perf_counter() - t0,
                      "compile_cpu_seconds": time.process_time() - c0}


def compile_program(obj, setup=None, beside: bool = False) -> Program:
    """Compile the program of ``obj``'s fit: forward mode for deterministic filters with at
    most :data:`FORWARD_MAX` coordinates, else ``jax.value_and_grad``; compiled ahead of time,
    with the XLA options :mod:`vehjax.execution` gives the estimator's workload. ``beside``:
    evaluated while another program compiles (:func:`vehjax.execution.direction_block`)."""
    flat, unravel = jax.flatten_util.ravel_pytree(obj.z0)
    n = flat.shape[0]
    if setup is None or setup.stochastic or n > FORWARD_MAX:
        options = None if setup is None else execution.compiler_options(execution.current(),
                                                                         setup.workload)
        compiled, stats = _compiled(_reverse(obj, unravel), (jnp.asarray(flat), obj.data),
                                    options)
        return Program(compiled, False, options, stats)
    return _compile_forward(obj, setup, None, beside)


def compile_directed(obj, setup, layout: Layout, beside: bool = False) -> Program:
    """Compile the program of ``obj`` (the fit's score tests' objective: the fit's coordinates
    and the held parameters', ``setup.anchored`` those) that serves the fit too (:class:`Program`
    with ``layout``): forward mode along directions given at each call, a block of the fit's
    coordinates' count at a time; compiled ahead of time with :mod:`vehjax.execution`'s XLA
    options. One compile fewer per fit with score tests: the fit's own program costs about as
    much per evaluation (``benchmarks/results``). ``beside`` as :func:`compile_program`'s."""
    return _compile_forward(obj, setup, layout, beside)


def _compile_forward(obj, setup, layout: Layout | None, beside: bool) -> Program:
    """The forward-mode :class:`Program` of ``obj`` (:func:`_forward`), its calls ``block``
    directions wide (:func:`vehjax.execution.direction_block` of the fit's coordinates' count:
    all of ``obj``'s without a ``layout``)."""
    flat, unravel = jax.flatten_util.ravel_pytree(obj.z0)
    strategy = execution.current()
    options = execution.compiler_options(strategy, setup.workload)
    block = execution.direction_block(strategy, flat.shape[0] if layout is None
                                      else len(layout.fit_pos), beside)
    anchor = jnp.zeros((0,), flat.dtype) if layout is None else jnp.asarray(layout.anchor,
                                                                           dtype=flat.dtype)
    V = jnp.zeros((block, flat.shape[0]), flat.dtype)
    compiled, stats = _compiled(_forward(obj, setup, unravel, anchored=layout is not None),
                                (jnp.asarray(flat), V, anchor, obj.data), options)
    return Program(compiled, True, options, stats, layout, block)


def _rows(pos, size: int, dtype) -> jnp.ndarray:
    """(len(pos), size): the rows ``pos`` of the identity; a negative position a zero row."""
    V = np.zeros((len(pos), size))
    for i, j in enumerate(pos):
        if j >= 0:
            V[i, j] = 1.0
    return jnp.asarray(V, dtype=dtype)


def _on_host(out):
    """A program's outputs as numpy arrays: waits for its evaluation (in the thread that made
    the call, so that calls made at once run at once)."""
    return jax.tree.map(np.asarray, out)


def at_once(calls, threads: int) -> list:
    """``[c() for c in calls]``, the calls made at once on up to ``threads`` host threads (one
    evaluation of a filter's scan keeps about one CPU core busy)."""
    workers = min(len(calls), threads)
    if workers <= 1:
        return [c() for c in calls]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(lambda c: c(), calls))


def _embedding(layout: Layout | None, n: int):
    """(the program's coordinates' count, the positions of the evaluated point's n coordinates
    among them, the program's point with those left to fill in) for a point of n coordinates:
    of the program's own objective (no ``layout``, or n its N), or of a fit on its score tests'
    program (n its fit's coordinates, the held ones at their anchor)."""
    if layout is None or n == layout.size:
        return n, np.arange(n), np.zeros(n)
    if n != len(layout.fit_pos):
        raise ValueError(f"compiled: a program over {layout.size} coordinates, "
                         f"{len(layout.fit_pos)} of them the fit's, cannot evaluate {n}")
    base = np.zeros(layout.size)
    base[layout.held_pos] = layout.anchor
    return layout.size, np.asarray(layout.fit_pos), base


def joined(outs, sizes, n_steps: int):
    """(loss, aux, grad, BHHH matrix) of a point evaluated in blocks of directions: ``outs``
    the forward-mode program's outputs (:func:`_forward`) per block, ``sizes`` each block's
    directions (its rows beyond are padding). The gradient the blocks' in turn; the BHHH
    matrix's entries between blocks from their per-step scores (:func:`score_outer_product`),
    within a block the program's, which hold the prior's curvature (a diagonal,
    :func:`prior_terms`). One block of no padding: the program's outputs as they are."""
    if len(outs) == 1 and outs[0][2].shape[0] == sizes[0]:
        return tuple(outs[0][:4])
    g = np.concatenate([o[2][:k] for o, k in zip(outs, sizes)])
    B = score_outer_product(np.concatenate([o[4][:k] for o, k in zip(outs, sizes)]), n_steps)
    ends = np.cumsum(sizes)
    for o, k, e in zip(outs, sizes, ends):
        B[e - k:e, e - k:e] = o[3][:k, :k]
    return outs[0][0], outs[0][1], g, B


def _evaluator(prog: Program, n: int, data, n_steps: int, dtype):
    """``(calls, join)`` of the program ``prog`` at n flat coordinates f: ``calls(f)`` the
    program's calls that evaluate f (zero-argument functions, to make at once: :func:`at_once`),
    ``join(outs) -> (loss, aux, grad, BHHH or None)`` from their outputs. A point of the
    program's own objective, of a fit on its score tests' program (:func:`_embedding`), or of
    the score tests' objective on it; in forward mode ``prog.block`` directions a call
    (:func:`joined`)."""
    executable = prog.compiled
    if not prog.forward:
        return (lambda f: [lambda: _on_host(executable(jnp.asarray(f, dtype=dtype), data))],
                lambda outs: tuple(outs[0]))
    size, pos, base = _embedding(prog.layout, n)
    anchor = jnp.asarray(np.zeros(0) if prog.layout is None else prog.layout.anchor, dtype=dtype)
    m = prog.block
    blocks = [list(pos[i:i + m]) for i in range(0, n, m)]
    Vs = [_rows(b + [-1] * (m - len(b)), size, dtype) for b in blocks]
    sizes = [len(b) for b in blocks]

    def calls(f):
        g = base.copy()
        g[pos] = np.asarray(f, dtype=float)
        at = jnp.asarray(g, dtype=dtype)
        return [lambda V=V: _on_host(executable(at, V, anchor, data)) for V in Vs]

    return calls, lambda outs: joined(outs, sizes, n_steps)


def compiled_loss(obj, setup=None, batch_hessian: bool = False, box=None,
                  compiled: Program | None = None) -> CompiledLoss:
    """The compiled loss of a fit (:class:`CompiledLoss`) on its program
    (:func:`compile_program`, or ``compiled``: the same objective's program compiled for
    another start, or with a :class:`Layout` the program of the fit's score tests, which
    serves both the fit and, on their objective, the tests: :func:`compile_directed`).
    ``batch_hessian`` (forward mode only): also give ``CompiledLoss.grads`` (its program
    compiled at its first call).

    The domain of a deterministic filter's fit: ``box`` = (low (n,), high (n,)) limits the
    coordinates (:func:`vehjax.tune.boundaries.coordinate_box`), and a point where more runs
    diverge than at the first point evaluated (the start) is outside too: there the loss is
    +inf (the gradient that of the nearest point of the box), which every optimiser's line
    search and the Newton polish reject. Without it a diverged run's log-likelihood, the sum of
    the steps before (0 on a one-step run), could undercut the finite ones and the optimiser
    would walk to values where the estimator cannot be built."""
    flat, unravel = jax.flatten_util.ravel_pytree(obj.z0)
    prog = compile_program(obj, setup) if compiled is None else compiled
    forward, options = prog.forward, prog.options
    stats = {"mode": "forward" if forward else "reverse", **prog.stats, "evaluations": 0,
             "batch_compile_seconds": 0.0, "batch_evaluations": 0, "options": options}
    last = []  # (point, result) of the latest evaluation: the optimiser's last point is the
    # Newton polish's first
    guard = setup is not None and not setup.stochastic
    base = []  # the runs diverged at the first point evaluated

    calls, join = _evaluator(prog, flat.shape[0], obj.data, obj.n_steps, flat.dtype)

    def run(points, threads):  # the compiled program at each point (clipped into the box),
        # its calls made at once on up to ``threads`` threads; no shared state touched
        inside = [box is None or not guard or bool(np.all((f >= box[0]) & (f <= box[1])))
                  for f in points]
        work = [calls(f if ok else np.clip(f, box[0], box[1])) for f, ok in zip(points, inside)]
        outs = at_once([c for w in work for c in w], threads)
        results, i = [], 0
        for ok, w in zip(inside, work):
            v, aux, g, B = join(outs[i:i + len(w)])
            i += len(w)
            results.append((ok, float(v), aux, np.asarray(g, dtype=float),
                            None if B is None else np.asarray(B, dtype=float),
                            int(np.sum(np.asarray(aux[1])))))
        return results

    def judged(f, r):  # counted, judged against the start's divergences, remembered
        inside, v, aux, g, B, n_div = r
        stats["evaluations"] += 1
        if not base:
            base.append(n_div)
        v = v if inside and (not guard or n_div <= base[0]) else np.inf
        out = (v, aux, g, B)
        last[:] = [f, out]
        return out

    def vgo(f):
        f = np.array(f, dtype=float)
        if last and np.array_equal(last[0], f):
            return last[1]
        return judged(f, run([f], execution.spare_threads(execution.current()))[0])

    def vg(f):
        return vgo(f)[:3]

    def many(points):
        points = [np.array(p, dtype=float) for p in points]
        threads = execution.current().side_by_side
        if len(points) <= 1 or threads <= 1:
            return [vg(p) for p in points]
        return [judged(p, r)[:3] for p, r in zip(points, run(points, threads))]

    grads = _batched_gradients(setup, unravel, obj, flat, options, stats) \
        if forward and batch_hessian else None
    return CompiledLoss(vg, unravel, np.asarray(flat, dtype=float), vgo if forward else None,
                        stats, grads, many)


def _batched_gradients(setup, unravel, obj, flat, options, stats):
    """``CompiledLoss.grads``: the gradient of the (penalised) loss at 2 n points at once
    (forward mode, vmapped over the points), compiled at its first call (the first Hessian of
    the fit)."""
    n = flat.shape[0]
    per_step, log_prior = setup.per_step, setup.log_prior

    def program(F, data):
        def one(f):
            ll, dll, div = forward_scores(lambda g, d: per_step(unravel(g), d), f, data)
            prior = prior_terms(log_prior, unravel, f, obj.n_steps, curvature=False)
            return _penalised(ll, dll, div, prior, obj.n_steps)[2]

        return jax.vmap(one)(F)

    box = {}

    def grads(F):
        if "compiled" not in box:
            t0 = time.perf_counter()
            box["compiled"] = jax.jit(program).lower(
                jnp.zeros((2 * n, n), flat.dtype), obj.data).compile(compiler_options=options)
            stats["batch_compile_seconds"] = time.perf_counter() - t0
        stats["batch_evaluations"] += 1
        return np.asarray(box["compiled"](jnp.asarray(F, dtype=flat.dtype), obj.data),
                          dtype=float)

    return grads
