"""Simpler descriptions nested in a model's terms, and the one move that prefers them.

A term may contain a simpler description of what it fits as a special case: an eddy term
``E_s = -tau I`` is a time offset; a field drift along ``(-B_N, B_E, 0)`` is the field
turned about Up, a heading drift; a disturbance free in ENU over a window is, where the
platform holds its attitude, one offset in the sensor's frame, a ``hard_iron_step``; two
abutting steps are one step with a second offset beside it. Each effect declares what it
contains, describes and merges with (:class:`~pipeline.model.effects.base.Effect`:
``contains``, ``in_window``, ``merges``, ``shares_with``); :data:`NESTED` turns them into
descriptions, and the search has one move for all of them
(:func:`simplest`): a description that loses no more than the evidence's margin replaces
what it is nested in (the simpler of a nested pair, Occam's razor with one criterion).
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Callable, Collection, Iterator, Sequence
from dataclasses import dataclass
from typing import cast

import numpy as np

from pipeline.core.vocabulary import EffectKind
from pipeline.model import parallel
from pipeline.model.effects import EFFECTS
from stages.diagnose.candidates import REFINED, RIVALS
from stages.diagnose.fit import FitResult, fit
from stages.diagnose.model import (
    F64,
    FitData,
    ModelState,
    Term,
    without_term,
)
from stages.diagnose.result import DiagnoseConfig, Finding
from stages.diagnose.sources import with_values
from stages.diagnose.statistics import (
    ScoreTest,
    effective_samples,
    evidence,
    evidence_between,
    heldout_ok,
    heldout_rms,
    rest_score_test,
)

#: An excess this close to an edge of a windowed term already in the model is the same
#: object moving (put down, taken away), s: it becomes that term's transition, not a term of
#: its own; terms whose windows lie closer than this are candidates for one event
#: (:attr:`~pipeline.model.effects.base.Effect.merges`).
RAMP_REACH_S = 1.0


def refine_step(
    w: tuple[float, float], residual_nT: np.ndarray, t_s: np.ndarray, reach_s: float = 1.0
) -> tuple[float, float]:
    """Change-point refinement of an offset window: maximise the explained residual energy.

    For a constant offset in ``[a, b)`` the least-squares gain is ``|sum r|^2 / n``; both
    edges are searched within ``reach_s`` of the scan's window using cumulative sums.
    """
    n = len(t_s)
    c = np.vstack([np.zeros(3), np.cumsum(residual_nT, axis=0)])
    ia = np.flatnonzero((t_s >= w[0] - reach_s) & (t_s <= w[0] + reach_s))
    ib = np.flatnonzero((t_s >= w[1] - reach_s) & (t_s <= w[1] + reach_s)) + 1
    if ia.size == 0 or ib.size == 0:
        return w
    ia = ia[:: max(1, ia.size // 150)]
    ib = ib[:: max(1, ib.size // 150)]
    S = c[ib][None, :, :] - c[ia][:, None, :]
    cnt = (ib[None, :] - ia[:, None]).astype(float)
    gain = np.where(cnt > 0, np.sum(S * S, axis=-1) / np.maximum(cnt, 1.0), -np.inf)
    i, j = np.unravel_index(int(np.argmax(gain)), gain.shape)
    a = float(t_s[ia[i]])
    b = float(t_s[ib[j]]) if ib[j] < n else float(t_s[-1]) + 1e-6
    return (a, b) if b > a else w


@dataclass(frozen=True)
class Description:
    """Another description of one term of a model (a simpler one, or the term in parts).

    Attributes
    ----------
    i : int
        The term it replaces, in that term's place.
    terms : tuple of Term
        The terms that describe it instead, in order (one for a simpler description).
    starts : tuple of ndarray
        Their starting values.
    also : int or None
        A second term it replaces as well (removed: two pieces become one).

    """

    i: int
    terms: tuple[Term, ...]
    starts: tuple[F64, ...]
    also: int | None = None

    @classmethod
    def one(cls, i: int, term: Term, start: F64, also: int | None = None) -> Description:
        """Describe term ``i`` by the single ``term``."""
        return cls(i, (term,), (start,), also)

    def state(self, st: ModelState) -> ModelState:
        """``st`` with this description in place (refit it to compare)."""
        terms, values = list(st.terms), list(st.values)
        terms[self.i:self.i + 1], values[self.i:self.i + 1] = self.terms, self.starts
        if self.also is not None:
            j = self.also + (len(self.terms) - 1 if self.also > self.i else 0)
            del terms[j], values[j]
        out = st.with_terms(terms, values)
        if EFFECTS[st.terms[self.i].kind].holds_frame:
            out = dataclasses.replace(out, T_enu=np.eye(3))  # the described term's frame goes
        return out


def _as_kind(kind: EffectKind) -> Callable[[FitResult, int, FitData], Iterator[Description]]:
    """Describe the whole term by one term of ``kind`` (no window), from zero."""
    def gen(cur: FitResult, i: int, data: FitData) -> Iterator[Description]:
        t = Term(kind)
        yield Description.one(i, t, t.null_value())
    return gen


def _in_window(cur: FitResult, i: int, data: FitData) -> Iterator[Description]:
    """Describe a windowed term as one term of the kind its effect names over its window.

    (:attr:`~pipeline.model.effects.base.Effect.in_window`: a disturbance fixed in ENU is,
    where the platform holds its attitude, one offset in the sensor frame.) The term's
    window was widened by a quarter of its length on each side around the scan's excess, so
    the edges are searched where a held offset changes in the residual without the term
    (:func:`refine_step`); a window shorter than the kind's
    :attr:`~pipeline.model.effects.base.Effect.min_window_s` is a bump, not that effect.
    """
    t = cur.state.terms[i]
    kind = EFFECTS[t.kind].in_window
    if kind is None or len(t.windows_s) != 1:
        return
    without = fit(without_term(cur.state, i), data)
    a, b = t.windows_s[0]
    w = refine_step((a, b), without.residual_nT, data.t_s, reach_s=0.3 * (b - a) + 1.0)
    if w[1] - w[0] >= EFFECTS[kind].min_window_s:
        new = Term(kind, (w,))
        yield Description.one(i, new, new.null_value())


def _one_for_two(cur: FitResult, i: int, data: FitData) -> Iterator[Description]:
    """Term ``i`` and a later term of its kind whose windows touch or overlap as one term.

    (:attr:`~pipeline.model.effects.base.Effect.merges`: pieces of one event.) The onset of
    the earlier and the release of the later are kept as the merged term's transitions; its
    start values are the effect's (:meth:`~pipeline.model.effects.base.Effect.merged_start`).
    """
    st = cur.state
    kind = st.terms[i].kind
    if len(st.terms[i].windows_s) != 1:
        return
    for j in range(i + 1, len(st.terms)):
        if st.terms[j].kind is not kind or len(st.terms[j].windows_s) != 1:
            continue
        (a_i, b_i), (a_j, b_j) = st.terms[i].windows_s[0], st.terms[j].windows_s[0]
        if a_j - b_i > RAMP_REACH_S or a_i - b_j > RAMP_REACH_S:
            continue
        first, last = (i, j) if a_i <= a_j else (j, i)
        t_f, t_l = st.terms[first], st.terms[last]
        a, b = t_f.windows_s[0][0], max(b_i, b_j)
        on = [r for r in t_f.ramps_s if abs(r[0] - t_f.windows_s[0][0]) < 1e-9]
        off = [r for r in t_l.ramps_s if abs(r[1] - t_l.windows_s[0][1]) < 1e-9]
        ramps = tuple(on + off)
        if len(ramps) == 2 and ramps[0][1] >= ramps[1][0]:
            continue
        with_ramps = t_f if t_f.ramps_s else t_l
        term = (Term(kind, ((a, b),)) if not ramps else
                dataclasses.replace(with_ramps, windows_s=((a, b),), ramps_s=ramps))
        start = EFFECTS[kind].merged_start((st.terms[i], st.values[i]),
                                           (st.terms[j], st.values[j]), term)
        yield Description.one(i, term, start, also=j)


def _shared_part_and_rest(cur: FitResult, i: int, data: FitData) -> Iterator[Description]:
    """Describe a term as the effect it shares a direction with and its rest.

    (:attr:`~pipeline.model.effects.base.Effect.shares_with`.) To first order the isotropic
    part ``tr(E_s)/3`` of an eddy term is a lag (``E_s = -tau I``); the lag in the model is
    exact ((M1) at ``t - tau``), the eddy term's regressor a first-order rate. The two
    descriptions have as many free parameters (1 + 8 against 9); the pair is the richer one
    (one term more) and is kept only when the data show the lag's second-order terms, by
    the margin.
    """
    term = cur.state.terms[i]
    eff = EFFECTS[term.kind]
    partner = Term(cast(EffectKind, eff.shares_with))
    if cur.state.value(partner.kind) is not None:
        return
    rest, shared = eff.fold_shared(np.asarray(cur.state.values[i], dtype=float),
                                   partner.null_value())
    yield Description(i, (partner, term), (shared, rest))


#: Whole terms nested in whole terms: the simpler kind (value) is a special case of the
#: other (key), :attr:`~pipeline.model.effects.base.Effect.contains`.
NESTED_SIMPLER: dict[EffectKind, EffectKind] = {
    kind: eff.contains for kind, eff in EFFECTS.items() if eff.contains is not None}

#: Kinds that are a sum of named terms: how a fitted term splits into them, and the score
#: test of the rest when its simpler part is already in the model (an eddy term beside a
#: time offset: the traceless part only). Every effect that shares a direction with another
#: (:attr:`~pipeline.model.effects.base.Effect.shares_with`) is one.
IN_PARTS: dict[EffectKind, tuple[Callable[[FitResult, int, FitData], Iterator[Description]],
                                 Callable[[FitResult, FitData, float], ScoreTest]]] = {
    kind: (_shared_part_and_rest, rest_score_test(kind))
    for kind, eff in EFFECTS.items() if eff.shares_with is not None
}


def _descriptions(kind: EffectKind) -> tuple[
        Callable[[FitResult, int, FitData], Iterator[Description]], ...]:
    """Return the other descriptions a term of ``kind`` has, in the order they are tried.

    From its effect's declarations: the simpler special case it contains, the term over its
    window as another kind, one term for two pieces, then the term in parts.
    """
    eff = EFFECTS[kind]
    gens: list[Callable[[FitResult, int, FitData], Iterator[Description]]] = []
    if eff.contains is not None:
        gens.append(_as_kind(eff.contains))
    if eff.in_window is not None:
        gens.append(_in_window)
    if eff.merges:
        gens.append(_one_for_two)
    if kind in IN_PARTS:
        gens.append(IN_PARTS[kind][0])
    return tuple(gens)


#: The other descriptions each kind of term has (:func:`_descriptions`).
NESTED: dict[EffectKind, tuple[Callable[[FitResult, int, FitData], Iterator[Description]], ...]]
NESTED = {kind: gens for kind in EFFECTS if (gens := _descriptions(kind))}


def hypothesis(term: Term, present: Collection[EffectKind]) -> tuple:
    """Return what adding ``term`` to a model with terms of the kinds ``present`` claims.

    Its kind and windows, and whether it would stand beside the simpler term nested in it
    (:data:`IN_PARTS`): an eddy term beside a time offset claims only its traceless rest,
    which a lag cannot explain, and is a different claim from the whole term that the lag
    replaced. The search remembers what it rejected and dropped by this key, so a term
    replaced by its simpler part can still come back as the rest.
    """
    beside = term.kind in IN_PARTS and NESTED_SIMPLER.get(term.kind) in present
    return (term.kind, term.windows_s, beside)


def _simpler(a: FitResult, b: FitResult) -> bool:
    """Whether model ``a`` is simpler than ``b``: fewer free parameters, then fewer terms."""
    return (a.state.n_free(), len(a.state.terms)) < (b.state.n_free(), len(b.state.terms))


def simplest(cur: FitResult, cv_cur: float, findings: list[Finding], data: FitData,
             cfg: DiagnoseConfig, dropped: set[tuple]
             ) -> tuple[FitResult, list[Finding]] | None:
    """Replace the first term that another description explains better, by Occam's razor.

    Each description is refitted with the rest of the model and compared with the current
    model by their evidence with one effective sample count
    (:func:`~stages.diagnose.statistics.evidence_between`): a simpler description is kept when
    it loses no more than ``bic_margin``, a richer one (as many parameters in more terms)
    when it gains the margin and predicts the held-out blocks better as a new term must
    (:func:`~stages.diagnose.statistics.heldout_ok`). A term of a kind already in the model
    is not offered again (one time offset, one heading drift). The replaced terms go into
    ``dropped`` (never re-added); the finding of the replaced term takes the new kinds in
    its place (their evidence is measured again in the final order).

    Returns
    -------
    (the refitted model, its findings) or None when no description is preferred.

    """
    kinds = {v.kind for v in cur.state.terms}
    offered = (s for i, t in enumerate(cur.state.terms) for gen in NESTED.get(t.kind, ())
               for s in gen(cur, i, data)
               if not any(not u.windows_s and u.kind is not t.kind and u.kind in kinds
                          for u in s.terms))
    # as many descriptions fitted at once as run side by side (pipeline.model.parallel),
    # judged in their order: none beyond them is fitted before these are judged
    while batch := list(itertools.islice(offered, parallel.cores())):
        fits = parallel.ordered(lambda s: fit(s.state(cur.state), data), batch)
        for s, res in zip(batch, fits, strict=True):
            simpler = _simpler(res, cur)
            limit = cfg.bic_margin if simpler else -cfg.bic_margin
            if evidence_between(res, cur, data) > limit or (
                    not simpler and heldout_ok(cur, res, data, cfg, cv_cur) is None):
                continue
            return res, _described(cur, findings, s, dropped)
    return None


def _described(cur: FitResult, findings: list[Finding], s: Description, dropped: set[tuple]
               ) -> list[Finding]:
    """Return the findings with term ``s.i`` (and ``s.also``) described as ``s`` says."""
    t = cur.state.terms[s.i]
    present = {u.kind for u in cur.state.terms}
    kept = {(u.kind, u.windows_s) for u in s.terms}
    if (t.kind, t.windows_s) not in kept:
        dropped.add(hypothesis(t, present))
    f = findings[s.i]
    out = list(findings)
    out[s.i:s.i + 1] = [f if u.kind is t.kind else dataclasses.replace(
        f, effect=u.kind.value, told_apart="") for u in s.terms]
    if s.also is not None:
        other = cur.state.terms[s.also]
        dropped.add(hypothesis(other, present))
        del out[s.also + (len(s.terms) - 1 if s.also > s.i else 0)]
    return out


#: Look-alikes: the kinds of term a new term of a kind can trade with along a shared
#: direction, the data paying for the new term by moving the look-alike
#: (:attr:`~pipeline.model.effects.base.Effect.trades_with`).
LOOKALIKES: dict[EffectKind, frozenset[EffectKind]] = {
    kind: eff.trades_with for kind, eff in EFFECTS.items() if eff.trades_with}


def earns_beside_lookalikes(with_term: FitResult, without: FitResult, i: int, data: FitData,
                            cfg: DiagnoseConfig) -> bool:
    """Whether term ``i`` of ``with_term`` earns its margin with its look-alikes held.

    ``without``: the same model without term ``i`` (the others in the same order), refitted.
    The terms of the kinds term ``i`` can trade with (:data:`LOOKALIKES`) are fixed at their
    values in ``without`` (a partial term with no combination fitted) and the rest refitted;
    a term that is there still raises the evidence by the margin at its own parameters (the count
    of ``with_term``), both with the smaller effective sample count; one that gained only by
    moving a look-alike along what the two share does not. A term without look-alikes in
    the model passes.
    """
    like = LOOKALIKES.get(with_term.state.terms[i].kind, frozenset())
    held = [k for k, t in enumerate(with_term.state.terms) if k != i and t.kind in like]
    if not held:
        return True
    terms, vals = list(with_term.state.terms), list(with_term.state.values)
    for k in held:
        v = np.asarray(without.state.values[k - (k > i)], dtype=float)
        terms[k] = terms[k].restricted(np.zeros((v.size, 0)), fixed=v)  # none fitted
        vals[k] = v
    fixed = fit(dataclasses.replace(with_term.state, terms=tuple(terms), values=tuple(vals)),
                data)
    n = min(effective_samples(fixed, data), effective_samples(without, data))
    return evidence(with_term, data, n, rss=fixed.rss) - evidence(
        without, data, n) <= -cfg.bic_margin


#: A term with rivals is named only when each fits worse by this many times the margin:
#: a short pass near an object makes a source, a step and a disturbance nearly equal.
DECISIVE_FACTOR = 5.0


def told_apart(cur: FitResult, res: FitResult, data: FitData) -> tuple[str, float, list[Term]]:
    """Compare the new last term of ``res`` with each of its rivals in its place.

    Each rival (:data:`~stages.diagnose.candidates.RIVALS`) is fitted in place of the new
    term on ``cur`` and compared by their evidence with one effective sample count. Returns
    the words on the comparison, the smallest difference (how decisively the term wins;
    infinite without rivals) and the rivals that fit better than the term.
    """
    kind = res.state.terms[-1].kind
    if kind not in RIVALS:
        return "", float(np.inf), []
    intro, rivals = RIVALS[kind](res, data)
    parts, worst, better = [], np.inf, []
    for alt, what in rivals:
        other = fit(cur.state.with_term(alt), data)
        d = evidence_between(other, res, data)
        worst = min(worst, d)
        if d < 0:
            better.append(alt)
        parts.append(f"{what} is less likely by {d:.0f} in -2 log evidence" if d > 0
                     else f"{what} is as likely ({d:.0f} in -2 log evidence): the pass is too "
                     "short to tell")
    return ". " + intro + "; " + "; ".join(parts), float(worst), better


#: Kinds whose candidate can explain part of any other candidate's excess
#: (:attr:`~pipeline.model.effects.base.Effect.absorbing`). Whatever a term local in time or
#: space or a global term explains is theirs; an absorbing term is for what none of them
#: can, so its fit is tried after the others, except after those it explains as well
#: (:func:`absorbed`).
ABSORBING = frozenset(kind for kind, eff in EFFECTS.items() if eff.absorbing)


def refinements(cur: FitResult, data: FitData) -> list[tuple[int, FitResult]]:
    """Return ``cur`` refitted with each term that has a finer form in it (``REFINED``).

    One model per such term, that term one step finer in its place (its values from zero),
    with the term's index.
    """
    out = []
    st = cur.state
    for i, t in enumerate(st.terms):
        finer = REFINED[t.kind][0](t, data) if t.kind in REFINED else None
        if finer is not None:
            out.append((i, fit(dataclasses.replace(
                st, terms=st.terms[:i] + (finer,) + st.terms[i + 1:],
                values=st.values[:i] + (finer.null_value(),) + st.values[i + 1:]), data)))
    return out


def explained_by_refinement(rich: FitResult, res: FitResult, data: FitData,
                            cfg: DiagnoseConfig, cv_cur: float) -> float | None:
    """Return the held-out RMS of ``rich`` if its refined term explains ``res``'s new one.

    ``rich``: the current model with one term refined (:func:`refinements`); ``res``: the
    current model with a new term added. A held term's complexity is the one the held-out
    blocks liked best when it came in, often by a hair over the next. A bump in time where
    the sensor passed a place the chosen map resolves too coarsely then earns a step's or a
    disturbance's margin, and which complexity won would decide whether it is named (an
    injected offset that tipped the choice made a step appear). The new term is the held
    term's when, added to the refined model at its fitted values, it no longer lowers the
    evidence by the margin, and the refined model predicts the held-out blocks no worse than the
    current one (within ``heldout_margin``). A magnet's step where the sensor came back
    without it keeps its margin beside any map.
    """
    if keeps_margin_beside(rich, res, data, cfg):
        return None  # the new term keeps its margin: no need for the held-out refits
    cv_rich = heldout_rms(rich.state, data, cfg)
    return cv_rich if cv_rich <= cv_cur * (1.0 + cfg.heldout_margin) else None


def keeps_margin_beside(by: FitResult, res: FitResult, data: FitData,
                        cfg: DiagnoseConfig) -> bool:
    """Whether the last term of ``res`` still raises the evidence by the margin beside ``by``.

    The term is added to ``by`` at the values it was fitted with, the two are refitted and
    compared with one effective sample count: the one test behind :func:`absorbed` and
    :func:`explained_by_refinement`.
    """
    both = fit(with_values(res.state.terms[-1], res.state.values[-1], by), data)
    return evidence_between(both, by, data) <= -cfg.bic_margin


def absorbed(by: FitResult, res: FitResult, data: FitData, cfg: DiagnoseConfig) -> bool:
    """Whether the last term of ``res`` no longer earns its margin beside ``by``.

    ``by``: the current model with an absorbing candidate (:data:`ABSORBING`). A term the
    absorbing one leaves something to explain (a compact source's ``1/r^3``, a disturbance
    where the sensor came back without it, a sensor term) still earns it.
    """
    term = res.state.terms[-1]
    if term.kind in ABSORBING or term in by.state.terms:
        return False
    return not keeps_margin_beside(by, res, data, cfg)


#: Requirements: a kind of term that acts only through terms of other kinds, and those kinds
#: (:attr:`~pipeline.model.effects.base.Effect.acts_through`; one of them must be in the
#: model). Such a term is a candidate only beside one of them, and the backward step keeps
#: the last of them while it stays (:func:`required`): a gradient beside a map would
#: otherwise be paid for by the map's prior, which then holds the linear part too.
REQUIRES: dict[EffectKind, frozenset[EffectKind]] = {
    kind: eff.acts_through for kind, eff in EFFECTS.items() if eff.acts_through}


def required(i: int, terms: Sequence[Term]) -> bool:
    """Whether term ``i`` is the last term of a kind that another of ``terms`` requires."""
    others = [t for k, t in enumerate(terms) if k != i]
    kinds = {t.kind for t in others}
    return any(terms[i].kind in need and not kinds & need
               for t in others if (need := REQUIRES.get(t.kind)) is not None)
