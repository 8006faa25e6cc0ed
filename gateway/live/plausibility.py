"""Plausibility: each sensor against what the others say, and the prediction against physics.

Range, rate, stuck and stale checks (:mod:`gateway.live.quality`) judge a sensor by
itself, so they miss the faults that look like heat: a transmitter drifting a
few tenths of a degree per second, a probe that reads a constant 3 °C high
after a knock, a bias that grows over hours. Two rules here catch those.

**1. Relation to the other sensors.** At fit time each sensor's rise is related
linearly to the other sensors' rises on the training data, with the held-out σ
of that relation (:mod:`models.estimators.sensor_relations`, stored in the model file).
Every cycle, for every sensor that passed the per-sensor checks::

    z = (ΔT_measured − ΔT_from_the_others) / σ_eff
    σ_eff = max(√(σ_held-out² + σ_ref² · (1 + Σ b_j²)), plausibility_min_sigma_C)

σ_held-out is the leave-one-run-out σ of the very relation used (the set of
other sensors that are good this cycle). σ_ref (``REFERENCE_SIGMA_C``) is the
error of the machine's cold reference, one reading per sensor: it shifts every
rise by a constant, which the relation's coefficients b_j carry into the
residual. A sensor is *suspect* when |z| > ``plausibility_sigma`` (default 5). When the
readings disagree, the sensor to blame is the one whose removal leaves the
others most consistent (the smallest worst |z| among the remaining sensors,
each judged from the remaining ones only), whether or not its own |z| is past
the threshold: a drifting sensor drags the neighbours whose relations lean on
it, and one of those may cross the threshold first; removing the drifting
sensor explains it, removing the neighbour does not. The culprit is removed and
the search repeats while the rest still disagree. Held sensors never judge the
others. When a new sensor is held, a sensor held earlier that has disagreed
ever since and agrees with the sensors left is released at once: the new
culprit explained its disagreement. Three or more sensors are needed to say
which one is wrong; with fewer the rule says nothing.

A suspect sensor goes BAD ("implausible: +7.4σ from its neighbours …") and is
*held*: it no longer predicts the others and the model bank switches to the
stored model fitted without it, exactly as for an open circuit. It is trusted
again only after it has agreed with the others (|z| ≤ ``AGREE_SHARE`` ×
``plausibility_sigma``) for ``plausibility_recover_s`` of machine time without
a break (default 900 s): a fault that comes and goes, or a bias hovering at the
threshold, does not flap the model in and out.

**2. A rate bound on the predicted error.** Thermal growth is slow: the fastest
rise of the simulated 8000 r/min spindle from cold is 0.8 µm/min, and real
spindles stay within a few µm/min. A plain model's prediction may move, from the
rises of up to ``RATE_HORIZON_S`` ago to this cycle's (the model and the speed
held at this cycle's, so a model switch or a speed step is not counted), by at
most::

    max_prediction_rate_um_per_s · Δt + prediction_noise_um

Both ends are predicted by the same model: every earlier cycle is predicted again
with this cycle's model, so a switch between regimes' models, or to the fallback
without a sensor, is never a move. A move past the bound is put on a sensor only
for a step of its own (:mod:`gateway.live.step_blame`): its change over the span
disagrees with what its neighbours' changes say (the relation without its
intercept, at rule 1's threshold; without a relation, a change past
``sigma × min_sigma_C`` that fewer than half of the others share), and with its
rise put back to its earlier value the move is within the bound. The step is
looked for against the latest earlier cycle past the bound, then the one most
past it. Of the sensors meeting both, the one whose rise put back leaves the
smallest move is held BAD as above ("implausible: moved the prediction …") and
the cycle predicts with the model without it (so the policy does not fall back
to hold-and-ramp).

A move that is no sensor's own step (heat the sensors agree on, the noise of a
fallback with large coefficients, a step most sensors share after a restart of
the transmitters or a re-zero) holds nobody: the prediction is used, and the
bound forgets the earlier cycles and counts from this one (logged, at most once
per ``RATE_HORIZON_S``, with how many sensors moved together). A sensor held for
a step that its neighbours have since shared (its change since the cycle it was
judged from is still past the noise floor and now agrees with theirs) is
trusted again at once; otherwise it is released by rule 1, or, where rule 1
cannot run, after ``plausibility_recover_s`` of good per-sensor checks.

The earlier cycles' rows and predictions are kept
from cycle to cycle (:mod:`gateway.live.earlier_rows`): the rule's cost does not
grow with the time the machine has run. Augmented models (lag states) are not
bounded this way: their speed terms legitimately step with the speed. Rates are per second
of the loop's clock: a simulated machine served faster than the gateway's wall
clock needs the bound scaled by the same factor.

**A reference taken while the spindle turns** (the gateway started for the
first time, or with a new state folder, in the middle of a run) holds each
sensor's true rise at that moment, d_i, so every rise reads low by d_i and the
fitted intercepts no longer fit. Rule 1 then judges the rises *since the
reference* instead: with r = ΔT − d and the reference instant t₀ (r(t₀) = 0),
the relation ΔT_i = a + Σ b_j ΔT_j + e becomes exactly::

    r_i = Σ b_j r_j + e(t) − e(t₀)

the same coefficients without the intercept, the residual now a difference of
two residuals, so σ_held-out is counted twice (σ_eff² = 2 σ² + the reference
term). The sensors are judged from the first cycle, at the cost of √2 in
sensitivity. The mode is decided at the first cycle with rises: a reference the
state folder marks as taken with the spindle turning (``taken_turning``), or,
for a reference file without the mark, rises all within ``FRESH_REFERENCE_C``
of zero while the spindle turned at the gateway's first cycle. It applies to
every later start on the same reference too. One line names how many machines
start this way (:class:`WarmStarts`); their models predict from the warm
reference as well, which only a reference taken cold mends.

**Without relations** (a model file saved before they were stored) rule 1 is
unavailable, which :attr:`Plausibility.available` says and the loop logs once;
rule 2 still runs.

Plain numbers in, verdicts out, machine time in seconds; no protocol I/O here.
Every hold and release is logged once.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from gateway.limits import PlausibilityLimits
from gateway.live.bank.model_bank import Banked, BankedModel, ModelBank
from gateway.live.earlier_rows import EarlierRows
from gateway.live.step_blame import (
    Attribution,
    attribute,
    changes,
    is_own_step,
    jump_floor_C,
    own_step_z,
)
from models.base import ModelInputs
from models.estimators.sensor_relations import SensorRelations

__all__ = [
    "AGREE_SHARE",
    "RATE_HORIZON_S",
    "REFERENCE_SIGMA_C",
    "Plausibility",
    "Suspect",
    "WarmStarts",
    "relations_from_bank",
]

log = logging.getLogger(__name__)

#: A held sensor "agrees" again when |z| is at most this share of the threshold:
#: a band between flagging and agreeing, so a reading near the threshold cannot flap.
AGREE_SHARE = 0.8

#: How far back (s) the prediction rate bound compares: long enough that a drift
#: spread over several fast cycles cannot slip through the per-cycle allowance.
RATE_HORIZON_S = 120.0

_Span = TypeVar("_Span", float, np.ndarray)

#: Error of one sensor's cold reference (one reading, °C): transmitter noise
#: (0.03 °C here) and half a 0.1 °C register step (0.03 °C σ), rounded up.
REFERENCE_SIGMA_C = 0.05

#: Rises all within this of zero (°C) at the first cycle: the reference was just taken.
FRESH_REFERENCE_C = 0.5

#: Fewest sensors among which one can be told to be the wrong one.
MIN_SENSORS_TO_BLAME = 3


@dataclass(frozen=True)
class Suspect:
    """A sensor the prediction rate bound blames, and why."""

    sensor: str
    reason: str


@dataclass
class _Hold:
    """A sensor held BAD by a plausibility rule."""

    since_s: float
    reason: str
    agree_since_s: float | None = None
    #: Held by the rate bound: the trusted rises of the earlier cycle its step was
    #: measured from (the step is judged shared, or not, against them).
    then_C: Mapping[str, float] | None = None


class WarmStarts:
    """The machines whose reference was taken with the spindle turning, named in one line.

    A gateway restarted mid-shift with a new state folder finds every machine
    warm: one line per machine would be a thousand at a thousand machines. The
    line is said once no machine has been noted for ``delay_s`` (a thousand first
    cycles under load take longer than any fixed delay after the first), and at the
    latest ``max_wait_s`` after the first, with the count of the machines noted.
    """

    def __init__(self, delay_s: float = 2.0, shown: int = 5, max_wait_s: float = 60.0) -> None:
        self.delay_s = delay_s
        self.shown = shown
        self.max_wait_s = max_wait_s
        self.machines: list[str] = []
        self._first_s: float | None = None
        self._timer: asyncio.TimerHandle | None = None

    def note(self, machine: str) -> None:
        self.machines.append(machine)
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no event loop (plain calls): say it now
            self.flush()
            return
        now = loop.time()
        if self._first_s is None:
            self._first_s = now
        if self._timer is not None:
            self._timer.cancel()
        self._timer = loop.call_at(
            min(now + self.delay_s, self._first_s + self.max_wait_s), self.flush
        )

    def flush(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
        self._first_s, self._timer = None, None
        names, self.machines = self.machines, []
        if not names:
            return
        more = len(names) - self.shown
        listed = ", ".join(names[: self.shown]) + (f" and {more} more" if more > 0 else "")
        log.warning(
            "%d machine(s) started with the temperature reference taken while the spindle "
            "turned (%s): the sensor plausibility check judges the rises since then (σ ×√2); "
            "the models predict from that warm reference too: delete the reference files and "
            "start with the machines cold to mend both",
            len(names),
            listed,
        )


WARM_STARTS = WarmStarts()


def relations_from_bank(bank: ModelBank, sensors: Iterable[str]) -> SensorRelations | None:
    """The stored relation covering most of the machine's sensors (then most rows, then id).

    Every model fitted on the same training data carries the same relation, so
    which one is taken matters only for a store mixing fits of different data.
    """
    machine = set(sensors)
    found: list[tuple[int, int, str, SensorRelations]] = []
    for model_id, banked in bank.models.items():
        if not isinstance(banked, BankedModel):
            continue
        relations = banked.relations()  # one per stored document, shared by machines
        if relations is None:
            continue
        covered = sum(1 for s in relations.sensors if s in machine)
        if covered >= MIN_SENSORS_TO_BLAME:
            found.append((-covered, -relations.rows, model_id, relations))
    return min(found, key=lambda f: f[:3])[3] if found else None


class Plausibility:
    """Both rules for one machine, with the holds they place (see the module docstring)."""

    def __init__(
        self, relations: SensorRelations | None, limits: PlausibilityLimits, machine: str = ""
    ) -> None:
        self.relations = relations
        self.limits = limits
        self.machine = machine
        self.armed: bool | None = None  # rule 1: decided at the first cycle with rises
        #: Rule 1 on rises since a reference taken warm (no intercepts; see the docstring).
        self.warm = False
        #: The reference's own mark: taken with the spindle turning (None: not known).
        self.reference_turning: bool | None = None
        self._turning_at_start: bool | None = None
        self.holds: dict[str, _Hold] = {}
        self.flags = 0  # how many times a sensor was newly held
        # The largest |z| of a sensor found sound: how close this machine runs to the threshold.
        self.largest_sound_z = 0.0
        #: Rule 2's earlier cycles, their rows and predictions kept (cost flat in run time).
        self._earlier = EarlierRows(RATE_HORIZON_S)
        #: Moves past the bound that were no sensor's own step (the bound re-referenced).
        self.re_references = 0
        self._re_references_logged = 0
        self._re_referenced_s: float | None = None

    @classmethod
    def for_machine(
        cls, machine: str, bank: ModelBank, sensors: Iterable[str], limits: PlausibilityLimits
    ) -> Plausibility:
        """The check for one machine, with the relation its model store carries (logged)."""
        relations = relations_from_bank(bank, sensors)
        if relations is None:
            log.warning(
                "%s: plausibility check unavailable: no stored model carries sensor relations "
                "(models saved before they were stored; refit to add them); the prediction "
                "rate bound still applies",
                machine,
            )
        else:
            log.info(
                "%s: plausibility check on %s (relations from %d training rows, %d runs)",
                machine,
                ", ".join(relations.sensors),
                relations.rows,
                relations.runs,
            )
        return cls(relations, limits, machine)

    @property
    def available(self) -> bool:
        """Whether rule 1 (relations between the sensors) can run."""
        return self.relations is not None and self.armed is not False

    # --- rule 1: each sensor against the others ------------------------------------------
    def judge(self, now_s: float, rises_C: Mapping[str, float]) -> dict[str, str]:
        """Place and release holds from this cycle's rises; the reason of every held sensor.

        ``rises_C``: rises (°C above the machine's reference) of the sensors that
        passed the per-sensor checks this cycle, held ones included (they are
        judged for agreement, never used to judge others).
        """
        if self.relations is None or self.armed is False:
            self._release_by_time(now_s, rises_C)
            return self.reasons()
        known = {s: v for s, v in rises_C.items() if s in self.relations.sensors}
        trusted = {s: v for s, v in known.items() if s not in self.holds}
        earlier = [s for s, hold in self.holds.items() if hold.agree_since_s is None]
        blamed = self._blame(trusted)
        for sensor, z, said in blamed:
            self._hold(now_s, sensor, f"implausible: {z:+.1f}σ from its neighbours ({said})")
            trusted.pop(sensor)
        if blamed:
            self._release_explained(earlier, known, trusted, [b[0] for b in blamed])
        for sensor in [s for s in self.holds if s in known]:
            self._judge_agreement(now_s, sensor, known[sensor], trusted)
        return self.reasons()

    def reasons(self) -> dict[str, str]:
        return {sensor: hold.reason for sensor, hold in self.holds.items()}

    def z_score(
        self, sensor: str, value_C: float, others: Mapping[str, float]
    ) -> tuple[float, str]:
        """(z, a readable account) of one sensor judged by ``others`` (rises, °C)."""
        assert self.relations is not None
        said = self.relations.predict(sensor, others)
        carried = REFERENCE_SIGMA_C**2 * (1.0 + sum(b * b for b in said.coefficients))
        predicted, spread = said.predicted_rise_C, said.sigma_C**2
        if self.warm:  # rises since a warm reference: no intercept, two residuals' spread
            predicted, spread = predicted - said.intercept_C, 2.0 * spread
        sigma = max(math.sqrt(spread + carried), self.limits.min_sigma_C)
        z = (value_C - predicted) / sigma
        since = " since the reference" if self.warm else ""
        text = f"rise{since} {value_C:.2f} °C, the others say {predicted:.2f} ± {sigma:.2f} °C"
        return z, text

    def _worst(self, rises_C: Mapping[str, float]) -> tuple[float, dict[str, tuple[float, str]]]:
        """Each sensor's z from all the others given, and the largest |z|."""
        scores = {
            s: self.z_score(s, v, {o: w for o, w in rises_C.items() if o != s})
            for s, v in rises_C.items()
        }
        return max(abs(z) for z, _ in scores.values()), scores

    def _blame(self, trusted: Mapping[str, float]) -> list[tuple[str, float, str]]:
        """The sensors to hold: removed one by one until the rest agree."""
        active = dict(trusted)
        blamed: list[tuple[str, float, str]] = []
        while len(active) >= MIN_SENSORS_TO_BLAME:
            worst, scores = self._worst(active)
            if worst <= self.limits.sigma:
                self.largest_sound_z = max(self.largest_sound_z, worst)
                break
            # Every sensor may be the explanation, not only those past the threshold.
            culprit = min(
                active,
                key=lambda c: (
                    self._worst({s: v for s, v in active.items() if s != c})[0],
                    -abs(scores[c][0]),
                ),
            )
            z, said = scores[culprit]
            if abs(z) <= self.limits.sigma:
                dragged = max(scores, key=lambda s: abs(scores[s][0]))
                said += f"; explains {dragged}'s {scores[dragged][0]:+.1f}σ"
            blamed.append((culprit, z, said))
            del active[culprit]
        return blamed

    def _release_explained(
        self,
        earlier: list[str],
        known: Mapping[str, float],
        trusted: Mapping[str, float],
        culprits: list[str],
    ) -> None:
        """Release the sensors held before whose disagreement the new culprits explain."""
        for sensor in earlier:
            others = {s: v for s, v in trusted.items() if s != sensor}
            if sensor not in known or len(others) < MIN_SENSORS_TO_BLAME - 1:
                continue
            z, _ = self.z_score(sensor, known[sensor], others)
            if abs(z) <= AGREE_SHARE * self.limits.sigma:
                hold = self.holds.pop(sensor)
                log.info(
                    "%s: sensor %s agrees without %s; trusted again (held since %.0f s, "
                    "its disagreement was theirs)",
                    self.machine,
                    sensor,
                    ", ".join(culprits),
                    hold.since_s,
                )

    def _judge_agreement(
        self, now_s: float, sensor: str, value_C: float, trusted: Mapping[str, float]
    ) -> None:
        hold = self.holds[sensor]
        others = {s: v for s, v in trusted.items() if s != sensor}
        if len(others) < MIN_SENSORS_TO_BLAME - 1:
            return  # too few trusted sensors to say it agrees: keep holding
        z, said = self.z_score(sensor, value_C, others)
        if abs(z) > AGREE_SHARE * self.limits.sigma:
            hold.agree_since_s = None
            hold.reason = f"implausible: {z:+.1f}σ from its neighbours ({said})"
            return
        if self._step_shared(sensor, {**others, sensor: value_C}):
            self._release(sensor, "shares its step with its neighbours now")
            return
        if hold.agree_since_s is None:
            hold.agree_since_s = now_s
        agreed_s = now_s - hold.agree_since_s
        if agreed_s >= self.limits.recover_s:
            self._release(sensor)
        else:
            hold.reason = (
                f"implausible until it agrees for {self.limits.recover_s:.0f} s "
                f"(agreeing for {agreed_s:.0f} s, {z:+.1f}σ)"
            )

    def _release_by_time(self, now_s: float, rises_C: Mapping[str, float]) -> None:
        """Without relations: a held sensor with good values is trusted after recover_s."""
        for sensor in [s for s in self.holds if s in rises_C]:
            hold = self.holds[sensor]
            others = {s: v for s, v in rises_C.items() if s not in self.holds}
            if self._step_shared(sensor, {**others, sensor: rises_C[sensor]}):
                self._release(sensor, "shares its step with its neighbours now")
                continue
            if hold.agree_since_s is None:
                hold.agree_since_s = now_s
            if now_s - hold.agree_since_s >= self.limits.recover_s:
                self._release(sensor)

    def _hold(
        self,
        now_s: float,
        sensor: str,
        reason: str,
        then_C: Mapping[str, float] | None = None,
    ) -> None:
        self.holds[sensor] = _Hold(since_s=now_s, reason=reason, then_C=then_C)
        self.flags += 1
        log.warning("%s: sensor %s is bad: %s", self.machine, sensor, reason)

    def _step_shared(self, sensor: str, now_C: Mapping[str, float]) -> bool:
        """Whether the step the rate bound held ``sensor`` for is its neighbours' too by now.

        Its change since the earlier cycle it was judged from must still be a step
        (past the noise floor: a spike that went away is not "shared", it waits for
        ``recover_s``) and agree with its trusted neighbours' changes over the same
        span: a restart or a re-zero they followed, never a fault of its own.
        """
        then_C = self.holds[sensor].then_C
        if then_C is None or sensor not in then_C:
            return False
        moved_C = changes(now_C, then_C)
        if abs(moved_C[sensor]) <= jump_floor_C(self.limits):
            return False
        z = own_step_z(self.relations, self.limits, sensor, moved_C)
        if z is not None:
            return abs(z) <= AGREE_SHARE * self.limits.sigma
        return not is_own_step(None, self.limits, sensor, moved_C)[0]

    def _release(self, sensor: str, why: str = "agrees again") -> None:
        hold = self.holds.pop(sensor)
        log.info(
            "%s: sensor %s %s; trusted (held since %.0f s)",
            self.machine,
            sensor,
            why,
            hold.since_s,
        )

    # --- rule 2: the predicted error's rate ---------------------------------------------
    def check_prediction(
        self,
        now_s: float,
        banked: Banked | None,
        rises_C: Mapping[str, float],
        speed_rpm: float | None,
    ) -> Suspect | None:
        """Blame (and hold) the sensor whose own step moves a plain model's prediction too
        fast, if any; a move that is no sensor's own step re-references the bound."""
        if not isinstance(banked, BankedModel):
            return None
        model = banked.model
        sensors = tuple(model.sensors_used_)
        if any(s not in rises_C for s in sensors) or (model.uses_speed and speed_rpm is None):
            return None
        now_x = np.array([rises_C[s] for s in sensors])
        moves = self._fastest_move(now_s, banked, sensors, now_x, speed_rpm)
        if not moves:
            return None
        verdict, move = Attribution(None, ""), moves[0]
        for move in moves:
            verdict = attribute(
                self.relations,
                self.limits,
                sensors,
                rises_C,
                move[2],
                self._allowed_um(move[1]),
                lambda rows: _predict(banked, sensors, rows, speed_rpm),
            )
            if verdict.sensor is not None:
                break
        moved_um, span_s, then_C = move
        if verdict.sensor is None:
            self._re_reference(now_s, moved_um, span_s, verdict, len(changes(rises_C, then_C)))
            return None
        reason = (
            f"implausible: moved the prediction {moved_um:+.1f} µm in {span_s:.0f} s "
            f"(bound {self._allowed_um(span_s):.1f} µm: "
            f"{self.limits.max_prediction_rate_um_per_s:g} µm/s + "
            f"{self.limits.prediction_noise_um:g} µm)"
        )
        self._hold(now_s, verdict.sensor, reason, then_C)
        return Suspect(verdict.sensor, reason)

    def _re_reference(
        self, now_s: float, moved_um: float, span_s: float, verdict: Attribution, known: int
    ) -> None:
        """No sensor's own step: forget the earlier cycles, this one is the new reference.

        Logged once per RATE_HORIZON_S at most (a model with large coefficients can
        do it now and then from noise alone), with the count since the last line.
        """
        self._earlier.clear()
        self.re_references += 1
        if self._re_referenced_s is not None and now_s - self._re_referenced_s < RATE_HORIZON_S:
            return
        since = self.re_references - self._re_references_logged
        self._re_referenced_s, self._re_references_logged = now_s, self.re_references
        log.info(
            "%s: the prediction moved %+.1f µm in %.0f s (bound %.1f µm) but no sensor stepped "
            "on its own (%d of %d sensors moved together; %s): nobody held, the rate bound "
            "counts from this cycle (%d such move(s) since the last line)",
            self.machine,
            moved_um,
            span_s,
            self._allowed_um(span_s),
            verdict.together,
            known,
            verdict.account,
            since,
        )

    def _fastest_move(
        self,
        now_s: float,
        banked: BankedModel,
        sensors: tuple[str, ...],
        now_x: np.ndarray,
        speed_rpm: float | None,
    ) -> list[tuple[float, float, Mapping[str, float]]]:
        """(moved µm, over s, that cycle's trusted rises) of the earlier cycles past the
        bound a step is looked for against: the latest one past it (a sudden step
        stands alone there, apart from what came before it), then the one most past it.

        Every earlier cycle in the horizon is predicted at this cycle's model and
        speed: the same model at both ends, so a switch of model (to a fallback
        without a sensor, or between regimes) is never a move. The predictions
        are kept from cycle to cycle while those are unchanged
        (:mod:`gateway.live.earlier_rows`), so the cost does not grow with the
        horizon's length. Empty: no earlier cycle is past the bound.
        """
        model = banked.model
        compared = self._earlier.compare(
            now_s,
            sensors,
            now_x,
            model,
            speed_rpm if model.uses_speed else None,
            lambda rows: _predict(banked, sensors, rows, speed_rpm),
        )
        if compared is None:
            return []
        spans_s = compared.spans_s
        moved = compared.now_um - compared.then_um
        excess = np.abs(moved) - self._allowed_um(spans_s)
        excess[np.isnan(excess)] = -np.inf  # a NaN prediction blames nobody
        worst = int(np.argmax(excess))  # the first of equal ones, as a scan would take
        if not excess[worst] > 0:
            return []
        latest = int(np.flatnonzero(excess > 0)[-1])
        return [
            (float(moved[k]), float(spans_s[k]), self._earlier.rises_of(int(compared.index[k])))
            for k in dict.fromkeys((latest, worst))
        ]

    def accept(
        self, now_s: float, rises_C: Mapping[str, float], speed_rpm: float | None = None
    ) -> None:
        """Remember the rises this cycle predicted from (trusted sensors only).

        The first cycle with rises also arms rule 1, or not (see the module docstring).
        """
        if self._turning_at_start is None:
            self._turning_at_start = speed_rpm is not None and speed_rpm > 0
        if self.armed is None and rises_C:
            self._arm(rises_C)
        self._earlier.append(now_s, {s: v for s, v in rises_C.items() if s not in self.holds})

    def _arm(self, rises_C: Mapping[str, float]) -> None:
        """Rule 1 on rises above a cold reference, or since a warm one (module docstring)."""
        self.armed = True
        if self.reference_turning is not None:
            self.warm = self.reference_turning
        else:
            fresh = max(abs(v) for v in rises_C.values()) <= FRESH_REFERENCE_C
            self.warm = bool(fresh and self._turning_at_start)
        if self.warm and self.relations is not None:
            WARM_STARTS.note(self.machine)

    def _allowed_um(self, span_s: _Span) -> _Span:
        lim = self.limits
        return lim.max_prediction_rate_um_per_s * span_s + lim.prediction_noise_um


def _predict(
    banked: BankedModel, sensors: tuple[str, ...], rows: np.ndarray, speed_rpm: float | None
) -> np.ndarray:
    """The model's prediction for each row of rises, all at this cycle's speed."""
    speed = 0.0 if speed_rpm is None else speed_rpm
    inputs = ModelInputs(rise_C=rows, sensors=sensors, speed_rpm=np.full(rows.shape[0], speed))
    return banked.model.predict(inputs)
