"""Every random stream of a run, derived from one seed by name: the only place seeds are derived.

A run has one seed (``camo optimize --seed``, the run spec's ``seed``); an evaluation has its own
(``camo evaluate --seed``). Every sampler seed and random generator the toolkit uses is one *stream* of the
table below, computed from that seed (and, for per-step streams, the iteration and view) by :func:`seed` or
:func:`generator`. No other module multiplies or offsets a seed.

The formulas are the ones the toolkit used before this table existed, unchanged, so results computed before
reproduce bit for bit (s = the run seed, e = the evaluation seed, i = iteration, v = view, k = stimulus)::

    stream              formula                                   what it seeds
    targets             7919 s + 1                                background targets, the initial render, the loss
                                                                  domain, the warm start's renders (common random
                                                                  numbers: paths missing the object agree in all)
    final_render        7919 s + 12345                            the result's final render (previews, renders.npz,
                                                                  the summary's losses)
    baseline_white      7919 s + 3                                painted baselines: the white copy of the object
    step                (1000003 s + 4099 i + 131 v) & 0x7FFFFFFF  a training render, primal (Stage 1 and Stage 2;
                                                                  i counts within the stage)
    step_grad           step ^ 0x5BD1E995 (& 0x7FFFFFFF)          the same render's adjoint pass
    silhouette_views    SeedSequence [s & 0xFFFFFFFF, i, 0x51]    the views of a projective step's silhouette term
    stage2_render       31 s + i                                  Stage 2: the render a pseudo ground truth starts from
    stage2_inpaint      977 s + i                                 Stage 2: the inpainter
    baseline            s                                         Owens 2014 (random order, greedy ties), GANmouflage
                                                                  (torch and NumPy generators)
    diffusion2d         s + v                                     diffusion2d: the inpainter for view v
    holdout_cameras     7919 s + 271                              the jitter of a run's held-out views (added
                                                                  2026-11-26; never the evaluation's stream, so a
                                                                  run never selects on the test views unless an
                                                                  evaluation seed happens to equal 7919 s + 271)
    holdout_render      7919 s + 977 + pair                       every held-out render; pair 0 and 1 are the two
                                                                  independent pairs of a check (each pair: with and
                                                                  without the object, one seed)
    evaluation_cameras  e                                         the jitter of the evaluation's novel views
    evaluation_render   (7919 e + 104729) & 0x7FFFFFFF            every evaluation render (all runs, background and
                                                                  with-object images alike)
    denoise_pilot       (7919 e + 3571 + pair) & 0x7FFFFFFF      the evaluation's object-spp pilot (two independent
                                                                  pairs of renders, with and without the object)
    observer            e + 7919 k                                the simulated observer on the k-th stimulus of a
                                                                  stimulus set (e = the build-stimuli / predict seed)
    turntable_render    (7919 t + 611953 + f) & 0x7FFFFFFF        frame f of a turntable video (``camo video --seed
                                                                  t``): the background and every result's panel of
                                                                  that frame alike (common random numbers)

``warm_start``, ``initial_render``, ``pose_search`` and ``pilot`` (the effect planner's pilot renders) are other
names of ``targets`` (:data:`ALIASES`): they must share its numbers; ``evaluation_pilot`` (the evaluation's pilot)
is ``evaluation_render``.

What the formulas do not give: for run seeds >= 1 the streams one method draws from never share a number at the
iteration and view counts runs use (``tests/test_seeds.py`` checks seeds 1-20, 200 iterations, 32 views), but at
run seed 0 (the default) several start at the same number -- ``step(0, 0)``, ``stage2_render(0)``, ``stage2_inpaint(0)`` and
``baseline`` are all 0 (:data:`SEED0_COINCIDENCES`). They feed different generators except ``step`` and
``stage2_render`` (both Mitsuba's sampler, in Stage 2's first iteration: its 16-spp preview of view 0 and the
4-spp training render of view 0 share their first samples). Keeping today's numbers was chosen over removing
that coincidence; ``tests/test_seeds.py`` pins both.

Seeds inside the renderer (Mitsuba's per-sensor seeds in :func:`optimizer.rendering.render.render_shaded`, the
budgeted silhouette sampler's salt in :mod:`optimizer.rendering.projective`) derive from a *render's* seed, not
from the run seed, and stay there. The scene generators (panoramas) and the study (simulated participants,
power analysis) have seeds of their own.
"""

from __future__ import annotations

import dataclasses
from typing import Any

#: Mask of a 31-bit non-negative seed (Mitsuba samplers take 32-bit seeds; 31 bits stay positive everywhere).
MASK31 = 0x7FFFFFFF


@dataclasses.dataclass(frozen=True)
class Stream:
    """One named stream: ``((run * s + sum(k * index) + offset) & mask) ^ xor) & mask`` (mask None: no mask).

    ``indices`` names the per-use counters the stream takes (``iteration``, ``view``, ``stimulus``) with their
    multipliers; ``source`` says whose seed ``s`` is (``"run"``, ``"evaluation"`` or ``"video"``); ``kind`` is ``"int"`` (a
    sampler seed) or ``"entropy"`` (a NumPy ``SeedSequence`` entropy list, :func:`entropy`)."""

    name: str
    purpose: str
    run: int = 1
    offset: int = 0
    indices: tuple[tuple[str, int], ...] = ()
    mask: int | None = None
    xor: int = 0
    source: str = "run"
    kind: str = "int"


STREAMS: dict[str, Stream] = {s.name: s for s in (
    Stream("targets", "background targets, initial render, loss domain, warm start", run=7919, offset=1),
    Stream("final_render", "the result's final render", run=7919, offset=12345),
    Stream("baseline_white", "painted baselines: the white copy of the object", run=7919, offset=3),
    Stream("step", "primal seed of a training render", run=1_000_003, indices=(("iteration", 4099), ("view", 131)),
           mask=MASK31),
    Stream("step_grad", "adjoint seed of a training render", run=1_000_003,
           indices=(("iteration", 4099), ("view", 131)), mask=MASK31, xor=0x5BD1E995),
    Stream("silhouette_views", "the views of a projective step's silhouette term", indices=(("iteration", 1),),
           kind="entropy"),
    Stream("stage2_render", "Stage 2: the render a pseudo ground truth starts from", run=31,
           indices=(("iteration", 1),)),
    Stream("stage2_inpaint", "Stage 2: the inpainter", run=977, indices=(("iteration", 1),)),
    Stream("baseline", "Owens 2014 orders and ties, GANmouflage's generators"),
    Stream("diffusion2d", "diffusion2d: the inpainter, per view", indices=(("view", 1),)),
    Stream("holdout_cameras", "jitter of a run's held-out views (optimizer/optimise/holdout.py)", run=7919,
           offset=271),
    Stream("holdout_render", "every held-out render of a run (background and with-object alike), per pair",
           run=7919, offset=977, indices=(("pair", 1),)),
    Stream("evaluation_cameras", "jitter of the evaluation's novel views", source="evaluation"),
    Stream("evaluation_render", "every evaluation render", run=7919, offset=104729, mask=MASK31, source="evaluation"),
    Stream("denoise_pilot", "the evaluation's object-spp pilot (evaluation/views.py object_spp_pilot), per pair",
           run=7919, offset=3571, indices=(("pair", 1),), mask=MASK31, source="evaluation"),
    Stream("observer", "the simulated observer, per stimulus", indices=(("stimulus", 7919),), source="evaluation"),
    Stream("turntable_render", "every panel of one turntable frame (evaluation/turntable.py)", run=7919,
           offset=611953, indices=(("frame", 1),), mask=MASK31, source="video"),
)}

#: Other names of a stream (the same numbers by design).
ALIASES = {"warm_start": "targets", "initial_render": "targets", "pose_search": "targets", "pilot": "targets",
           "evaluation_pilot": "evaluation_render"}

#: Streams of one run that start at the same number at run seed 0 (today's formulas; see the module doc).
SEED0_COINCIDENCES = ("step", "stage2_render", "stage2_inpaint", "baseline")


def stream(name: str) -> Stream:
    """The stream called ``name`` (or an alias of it); ValueError for an unknown name."""
    s = STREAMS.get(ALIASES.get(name, name))
    if s is None:
        raise ValueError(f"unknown seed stream {name!r}; streams: {', '.join(sorted([*STREAMS, *ALIASES]))}")
    return s


def _linear(st: Stream, base: int, index: dict[str, Any]) -> int:
    names = {k for k, _ in st.indices}
    extra = set(index) - names
    if extra:
        raise ValueError(f"seed stream {st.name!r} takes {', '.join(sorted(names)) or 'no index'}, "
                         f"not {', '.join(sorted(extra))}")
    if isinstance(base, bool) or int(base) != base:
        raise ValueError(f"seed must be an integer, got {base!r}")
    return int(base) * st.run + sum(int(index.get(k, 0)) * m for k, m in st.indices) + st.offset


def seed(name: str, base: int, **index: int) -> int:
    """Sampler seed of stream ``name`` for seed ``base`` (the run's or the evaluation's) and its indices
    (``iteration=``, ``view=``, ``stimulus=``, ``frame=``; absent indices count as 0)."""
    st = stream(name)
    if st.kind != "int":
        raise ValueError(f"seed stream {name!r} is a NumPy entropy list: use seeds.entropy or seeds.generator")
    v = _linear(st, base, index)
    if st.mask is not None:
        v &= st.mask
    if st.xor:
        v ^= st.xor
        if st.mask is not None:
            v &= st.mask
    return v


def entropy(name: str, base: int, **index: int) -> list[int] | int:
    """What :func:`numpy.random.default_rng` takes for stream ``name``: an entropy list for ``entropy``
    streams, the :func:`seed` otherwise."""
    st = stream(name)
    if st.kind == "int":
        return seed(name, base, **index)
    _linear(st, base, index)  # validates the indices
    if st.name == "silhouette_views":
        return [int(base) & 0xFFFFFFFF, int(index.get("iteration", 0)), 0x51]
    raise ValueError(f"seed stream {name!r} has no entropy rule")  # pragma: no cover - every entropy stream has one


def generator(name: str, base: int, **index: int):
    """A NumPy ``Generator`` seeded from stream ``name`` (NumPy is imported when called)."""
    import numpy as np

    return np.random.default_rng(entropy(name, base, **index))


def table() -> list[dict[str, Any]]:
    """The streams as rows (name, purpose, source, formula), for documentation and ``config.toml`` readers."""
    rows = []
    for st in STREAMS.values():
        if st.kind == "entropy":
            formula = "SeedSequence [s & 0xFFFFFFFF, iteration, 0x51]"
        else:
            terms = [f"{st.run} s" if st.run != 1 else "s", *(f"{m} {k}" if m != 1 else k for k, m in st.indices)]
            if st.offset:
                terms.append(str(st.offset))
            formula = " + ".join(terms)
            if st.mask is not None:
                formula = f"({formula}) & {st.mask:#x}"
            if st.xor:
                formula = f"({formula} ^ {st.xor:#x}) & {st.mask:#x}"
        rows.append({"name": st.name, "purpose": st.purpose, "source": st.source, "formula": formula})
    return rows
