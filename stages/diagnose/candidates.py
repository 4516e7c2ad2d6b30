"""How each effect is proposed to the search: at an event the scan found, and scored.

The search (:mod:`stages.diagnose.search`) asks two registries, keyed by effect, instead of
naming effects itself:

- :data:`AT_EVENT`: the terms an effect offers where the residual scan opened a window (a
  disturbance over the padded window, a step where the offset is held, a source fixed in
  the room located there, present throughout or only around the window);
- :data:`SCORERS`: how an effect's candidate is scored when the plain score test at zero
  does not fit it (the gradient in its own bearing, a source from its located moment).

Both are filled here with ``@at_event`` and ``@scorer``; an effect without an entry is a
global term, scored by :func:`~stages.diagnose.statistics.score_test`. The effects' physics
(:mod:`pipeline.model.effects`) cannot import the search; this module is the search's side
of each effect's plug-in.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.model.effects import EFFECTS
from stages.diagnose.field_map import finer_map_term
from stages.diagnose.fit import FitResult
from stages.diagnose.model import F64, FitData, ModelState, Term
from stages.diagnose.sources import (
    MAX_NEAR_FAR_RATIO,
    locate_source,
    near_far_ratio,
    source_term,
    with_values,
)
from stages.diagnose.sources import rivals as source_rivals
from stages.diagnose.statistics import ScoreTest, gradient_candidate, score_test


@dataclass(frozen=True)
class Event:
    """Where the residual scan opened a window, as the candidates need it.

    Attributes
    ----------
    window_s : (float, float)
        The scan's window, s (half-open).
    held_s : (float, float)
        Where an offset is held in it (:func:`~stages.diagnose.nested.refine_step`).
    padded_s : (float, float)
        The window padded as a bell-shaped transient needs (it starts and ends earlier and
        later than the scan sees), within the recording.
    knot_step_s : float
        The knot spacing of a disturbance over ``padded_s``, s.
    edge_of_step : bool
        The window is a transition of a step already in the model (its ramp is tried
        instead of a new step).

    """

    window_s: tuple[float, float]
    held_s: tuple[float, float]
    padded_s: tuple[float, float]
    knot_step_s: float
    edge_of_step: bool


#: A candidate: the term, and the start values of its refit (None: from zero).
Candidate = tuple[Term, F64 | None]
EventCandidates = Callable[[FitResult, FitData, Event], list[Candidate]]
Scorer = Callable[[FitResult, FitData, Term, float, F64 | None],
                  tuple[ScoreTest, ModelState | None]]

#: effect -> its candidates at an event of the scan, asked in EffectKind's order
AT_EVENT: dict[EffectKind, EventCandidates] = {}
#: effect -> how its candidate is scored (and the state its refit starts at)
SCORERS: dict[EffectKind, Scorer] = {}

Rivals = Callable[[FitResult, FitData], tuple[str, list[tuple[Term, str]]]]
Finer = Callable[[Term, FitData], "Term | None"]


def _finer_map_words(term: Term) -> str:
    """Return what a refined ``field_map`` is: its modes along the longest axis, its functions."""
    return (f"{max(term.n_axis)} modes along the longest axis "
            f"({int(np.prod(term.n_axis))} functions)")


#: effect -> the terms that could replace its new term in its place, over the windows where
#: it acts, with the words on what tells it apart (nested.told_apart). Restore keeps a
#: source in the field and takes a step out of it: naming the wrong one of such rivals
#: moves the restored field.
RIVALS: dict[EffectKind, Rivals] = {EffectKind.LOCAL_SOURCE: source_rivals}
#: effect -> its finer form, one step up its own ladder (None at the top), and the words that
#: say what the finer form is (nested.refinements): a field map one complexity finer
#: resolves the field where the sensor was more closely.
REFINED: dict[EffectKind, tuple[Finer, Callable[[Term], str]]] = {
    EffectKind.FIELD_MAP: (finer_map_term, _finer_map_words)}


def at_event(kind: EffectKind) -> Callable[[EventCandidates], EventCandidates]:
    """Register ``kind``'s candidates at an event (:data:`AT_EVENT`)."""
    def put(fn: EventCandidates) -> EventCandidates:
        AT_EVENT[kind] = fn
        return fn
    return put


def scorer(kind: EffectKind) -> Callable[[Scorer], Scorer]:
    """Register how ``kind``'s candidate is scored (:data:`SCORERS`)."""
    def put(fn: Scorer) -> Scorer:
        SCORERS[kind] = fn
        return fn
    return put


def event_candidates(cur: FitResult, data: FitData, event: Event) -> list[Candidate]:
    """Return every effect's candidates at ``event``, in EffectKind's order."""
    return [c for kind in EffectKind if kind in AT_EVENT
            for c in AT_EVENT[kind](cur, data, event)]


def scored(cur: FitResult, data: FitData, term: Term, sigma: float, start: F64 | None
           ) -> tuple[ScoreTest, ModelState | None]:
    """Score ``term`` beside ``cur`` (its effect's :data:`SCORERS` entry, else at zero)."""
    if term.kind in SCORERS:
        return SCORERS[term.kind](cur, data, term, sigma, start)
    return score_test(cur, term, data, sigma), None


@at_event(EffectKind.DISTURBANCE)
def _disturbance(cur: FitResult, data: FitData, event: Event) -> list[Candidate]:
    """Offer a field in ENU over the padded window (linear hats every ``knot_step_s``)."""
    return [(Term(EffectKind.DISTURBANCE, (event.padded_s,), knot_step_s=event.knot_step_s),
             None)]


@at_event(EffectKind.HARD_IRON_STEP)
def _step(cur: FitResult, data: FitData, event: Event) -> list[Candidate]:
    """Offer an offset held where the scan saw it held.

    Not at an edge of a step already in the model (its transition), and not for less than
    the step's :attr:`~pipeline.model.effects.base.Effect.min_window_s`: that is a bump, not
    an object left near the sensor.
    """
    a, b = event.held_s
    if event.edge_of_step or b - a < EFFECTS[EffectKind.HARD_IRON_STEP].min_window_s:
        return []
    return [(Term(EffectKind.HARD_IRON_STEP, (event.held_s,)), None)]


@at_event(EffectKind.LOCAL_SOURCE)
def _source(cur: FitResult, data: FitData, event: Event) -> list[Candidate]:
    """Offer the same excess as a source fixed in the room, located on a grid.

    Present throughout, or only around the window (put down and taken away); only where
    the sensor came near it (:data:`~stages.diagnose.sources.MAX_NEAR_FAR_RATIO`).
    """
    loc = locate_source(cur, data, event.window_s)
    if loc is None or near_far_ratio(source_term(loc[1], (event.padded_s,)), loc[0],
                                     data) > MAX_NEAR_FAR_RATIO:
        return []
    return [(source_term(loc[1], presence), loc[0]) for presence in ((), (event.padded_s,))]


@scorer(EffectKind.LOCAL_SOURCE)
def _score_source(cur: FitResult, data: FitData, term: Term, sigma: float,
                  start: F64 | None) -> tuple[ScoreTest, ModelState | None]:
    """Test at zero moment at the located place; start the refit from the grid's moment."""
    v0 = np.asarray(start, dtype=float)
    st = score_test(cur, term, data, sigma,
                    start=with_values(term, np.r_[v0[:3], 0, 0, 0, v0[6:]], cur))
    return st, with_values(term, v0, cur)


@scorer(EffectKind.FIELD_GRADIENT)
def _score_gradient(cur: FitResult, data: FitData, term: Term, sigma: float,
                    start: F64 | None) -> tuple[ScoreTest, ModelState | None]:
    """Test, with positions, in the bearing the score is largest (the test carries the term)."""
    if data.p_m is None:
        return score_test(cur, term, data, sigma), None
    return gradient_candidate(cur, data, sigma), None

