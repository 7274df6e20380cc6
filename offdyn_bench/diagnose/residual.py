"""The residual of a hypothesis (the source model plus some effects) on measured transitions.

A hypothesis is a tuple of effects added to the source. Its prediction for a row restarts the
source model at the recorded state, replays the recorded commands through the hypothesis's action
channel, steps the physics ``horizon`` control steps open loop and reads the observation through
the observation map and the hypothesis's observation channel. Residuals are normalized per
observation dimension by the spread (standard deviation) of that dimension's change over the same
horizon, so a joint angle and a velocity weigh alike.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence
from typing import Any, Literal

import numpy as np

from offdyn_bench.diagnose.data import DiagnosisInputError, Transitions
from offdyn_bench.diagnose.source import SourceSimulator, rebuild_states
from offdyn_bench.effects import Effect
from offdyn_bench.effects.channel import ChannelEffect
from offdyn_bench.effects.model import ModelEffect

Hypothesis = tuple[Effect, ...]
SearchTarget = Literal["auto", "observations", "states"]
SEARCH_TARGETS: tuple[str, ...] = ("auto", "observations", "states")

# The simulator restarted exactly reproduces its own steps to ~1e-15: anything below this is numerics.
NUMERICAL_FLOOR = 1e-6


@dataclasses.dataclass(frozen=True)
class ErrorSummary:
    """Normalized RMSE of one hypothesis: overall, per observation dimension, and trimmed.

    ``trimmed_nrmse`` leaves out the worst 1% of rows: a residual a few rows carry (a command
    that fell between the recorded ones that located a threshold, a rare contact event) is not a
    systematic gap; a wrong model shows in every row.
    """

    nrmse: float
    per_dimension: np.ndarray
    trimmed_nrmse: float
    trimmed_per_dimension: np.ndarray
    rows: int

    @staticmethod
    def of(residual: np.ndarray) -> ErrorSummary:
        if not residual.size:
            return ErrorSummary(0.0, np.zeros(residual.shape[1]), 0.0, np.zeros(residual.shape[1]), 0)
        per_row = np.mean(residual**2, axis=1)
        kept = np.argsort(per_row, kind="stable")[: max(1, int(np.ceil(0.99 * len(per_row))))]
        return ErrorSummary(nrmse=float(np.sqrt(np.mean(per_row))),
                            per_dimension=np.sqrt(np.mean(residual**2, axis=0)),
                            trimmed_nrmse=float(np.sqrt(np.mean(per_row[kept]))),
                            trimmed_per_dimension=np.sqrt(np.mean(residual[kept] ** 2, axis=0)),
                            rows=len(per_row))


def _is_stochastic(effect: Effect) -> bool:
    return effect.kind in ("action_noise", "obs_noise")


def physics_key(hypothesis: Hypothesis, rebuilt: bool) -> tuple[Effect, ...]:
    """The effects that change what the physics does (the rest act on the observation only)."""
    keep = []
    for effect in hypothesis:
        if _is_stochastic(effect):
            continue
        if isinstance(effect, ModelEffect) or getattr(effect, "channel", None) == "action":
            keep.append(effect)
        elif rebuilt and effect.kind == "obs_bias":  # a biased observation moves the rebuilt state
            keep.append(effect)
    return tuple(keep)


class ResidualEvaluator:
    """Predictions and normalized residuals of hypotheses on named subsets of the data."""

    def __init__(self, source: SourceSimulator, data: Transitions, *, horizon: int = 10,
                 heldout_fraction: float = 0.3, screen_rows: int = 2000, fit_rows: int = 5000,
                 seed: int = 0, search_horizon: int = 1, search_target: SearchTarget = "auto") -> None:
        if search_target not in SEARCH_TARGETS:
            raise DiagnosisInputError(f"search_target must be one of {', '.join(SEARCH_TARGETS)}, got {search_target!r}")
        source.check_data(data)
        self.source = source
        self.data = data
        self.horizon = horizon
        self.episode = data.episode_index
        self.step = data.step_in_episode
        self.episode_start_row = np.arange(data.size) - self.step
        self.dims = source.observation_map.mapped
        self.notes: list[str] = []
        self.rebuilt = not data.has_state
        if data.has_state:
            qpos_qvel = np.concatenate([data.qpos, data.qvel], axis=1)  # type: ignore[list-item]
            usable = np.ones(data.size, dtype=bool)
        else:
            qpos_qvel, usable, notes = rebuild_states(source, data.observations)
            self.notes.append("no stored qpos/qvel: physics state rebuilt from the observations")
            self.notes.extend(notes)
        self.usable = usable
        self.states = source.full_states(qpos_qvel[:, :source.base_model.nq], qpos_qvel[:, source.base_model.nq:])
        self._rebuilt_cache: dict[tuple[Effect, ...], np.ndarray] = {}

        # Held-out data are whole episodes, so held-out error measures generalization in time too.
        rng = np.random.default_rng(seed)
        episodes = np.unique(self.episode)
        shuffled = rng.permutation(episodes)
        n_heldout = max(1, int(round(heldout_fraction * len(episodes)))) if len(episodes) > 1 else 0
        heldout_episodes = set(shuffled[:n_heldout].tolist())
        is_heldout = np.isin(self.episode, list(heldout_episodes))
        if n_heldout == 0:  # a single episode: hold out its last part instead
            is_heldout = np.arange(data.size) >= int(data.size * (1 - heldout_fraction))
        train = np.flatnonzero(usable & ~is_heldout)
        heldout = np.flatnonzero(usable & is_heldout)
        if len(train) < 20 or len(heldout) < 10:
            raise DiagnosisInputError(f"too few usable transitions to diagnose ({len(train)} training and {len(heldout)} "
                                      "held-out rows); diagnosis needs a few hundred transitions over several episodes")
        self.subsets: dict[str, np.ndarray] = {
            "train": train,
            "heldout": heldout,
            "screen": np.sort(rng.choice(train, size=min(screen_rows, len(train)), replace=False)),
            "fit": np.sort(rng.choice(train, size=min(fit_rows, len(train)), replace=False)),
        }
        self.windows = {name: self._window_starts(rows) for name, rows in (("train", train), ("heldout", heldout))}
        # The search (screen, fits, choice, stop) compares predictions search_horizon steps ahead:
        # at a high control rate one step moves the state less than the sensor noise, and effects
        # that a single step hides add up over several.
        self.search_horizon = search_horizon
        if search_horizon == 1:
            self.search_starts = dict(self.subsets)
        else:
            train_k, heldout_k = self._window_starts(train, search_horizon), self._window_starts(heldout, search_horizon)
            if len(train_k) < 20 or len(heldout_k) < 10:
                raise DiagnosisInputError(f"too few windows of {search_horizon} steps to search on ({len(train_k)} "
                                          f"training and {len(heldout_k)} held-out); use a shorter search horizon")
            self.search_starts = {
                "train": train_k, "heldout": heldout_k,
                "screen": np.sort(rng.choice(train_k, size=min(screen_rows, len(train_k)), replace=False)),
                "fit": np.sort(rng.choice(train_k, size=min(fit_rows, len(train_k)), replace=False)),
            }
        if not any(len(w) for w in self.windows.values()):
            self.notes.append(f"no episode is {horizon} steps long: the H-step error is not measured (reported as null)")
        change = data.next_observations[:, self.dims] - data.observations[:, self.dims]
        self.spread = _safe_spread(change[usable])
        starts = np.concatenate(list(self.windows.values()))
        if len(starts):
            h_change = data.next_observations[starts + horizon - 1][:, self.dims] - data.observations[starts][:, self.dims]
            self.horizon_spread = _safe_spread(h_change)
        else:
            self.horizon_spread = self.spread
        if search_horizon == 1:
            self.search_spread = self.spread
        else:
            starts_k = self.search_starts["train"]
            self.search_spread = _safe_spread(data.next_observations[starts_k + search_horizon - 1][:, self.dims]
                                              - data.observations[starts_k][:, self.dims])
        self._cache: dict[tuple, np.ndarray] = {}
        if self.rebuilt:
            self._check_unobserved_coordinates()
        self._reference: dict[tuple, list[tuple[np.ndarray, np.ndarray]]] = {}
        self._actions_cache: dict[tuple[Effect, ...], np.ndarray] = {}
        self.observation_check = self._check_observation_channel()
        note = self.observation_check.note(source.observation_map.names)
        if note is not None:
            self.notes.append(note)
        self.search_on_states = False
        if search_target == "states" and self.rebuilt:
            raise DiagnosisInputError("search_target='states' needs stored qpos/qvel in the data; these data have none")
        if search_target == "states" or (search_target == "auto" and self.observation_check.sensors_differ):
            self._search_on_stored_states(rng, screen_rows, fit_rows)

    def _search_on_stored_states(self, rng: np.random.Generator, screen_rows: int, fit_rows: int) -> None:
        """Make the search compare predicted physics with the stored states ``search_horizon``
        steps later, read through the observation map, instead of with the recorded observations.

        Where the sensors do not read the stored state exactly (noise, a latency, an offset), the
        recorded observation mixes the sensors into every residual: at a high control rate the
        noise of one reading can exceed what the dynamics move in a step, and the dynamics effects
        drown in it. The stored states carry the physics without the sensors, so the dynamics are
        searched on them, and the sensors are read off the difference between the two recordings
        (:meth:`_check_observation_channel`). The reported errors stay those of the recorded
        observations. Windows need their end state, so each episode's last ``search_horizon``
        rows cannot start one; with too few windows left the search stays on the observations.
        """
        k = self.search_horizon

        def has_end(starts: np.ndarray) -> np.ndarray:
            ends = starts + k
            ok = ends < self.data.size
            starts, ends = starts[ok], ends[ok]
            return starts[(self.episode[ends] == self.episode[starts]) & self.usable[ends]]

        train, heldout = has_end(self.search_starts["train"]), has_end(self.search_starts["heldout"])
        if len(train) < 20 or len(heldout) < 10:
            self.notes.append("too few windows end inside an episode to search on the stored states: the search "
                              "compares recorded observations")
            return
        screen = np.sort(rng.choice(train, size=min(screen_rows, len(train)), replace=False))
        fit = np.sort(rng.choice(train, size=min(fit_rows, len(train)), replace=False))
        self.search_starts = {"train": train, "heldout": heldout, "screen": screen, "fit": fit}
        self.search_spread = _safe_spread(self.state_reading(train + k) - self.state_reading(train))
        self.search_on_states = True
        self.notes.append("the search compares predictions with the stored states (the sensors differ from them); "
                          "the errors reported are against the recorded observations")

    def state_reading(self, rows: np.ndarray) -> np.ndarray:
        """The observation (mapped dimensions) read off the stored state of ``rows``, no sensor effects."""
        return self.source.observation_map.observe(self.source.qpos_qvel(self.states[rows]))

    def _check_unobserved_coordinates(self) -> None:
        """The rebuilt state sets positions the observation lacks (Hopper's x) to their reference
        value; say whether the dynamics really ignore them."""
        nq = self.source.base_model.nq
        unobserved = [j for j in range(nq) if j not in set(self.source.observation_map.source.tolist())]
        if not unobserved:
            return
        rows = self.subsets["screen"][:200]
        shifted = self.states[rows].copy()
        shifted[:, 1 + np.array(unobserved)] += 0.5
        controls = self.data.actions[rows][:, None]
        model = self.source.base_model
        both = self.source.predict(model, np.concatenate([self.states[rows], shifted]), np.concatenate([controls, controls]))
        observed = self.source.observation_map.observe(self.source.qpos_qvel(both[:, -1]))
        change = float(np.max(np.abs(observed[: len(rows)] - observed[len(rows):]) / self.spread))
        labels = [self.source.observation_map_labels[j] for j in unobserved]
        if change > 1e-6:
            self.notes.append(f"the dynamics depend on {', '.join(labels)}, which the observation lacks: "
                              f"predictions from rebuilt states are off by up to {change:.3g} (normalized); "
                              "store qpos/qvel with the data")
        else:
            self.notes.append(f"checked: the dynamics do not depend on {', '.join(labels)}")

    def _window_starts(self, rows: np.ndarray, horizon: int | None = None) -> np.ndarray:
        """Non-overlapping windows of ``horizon`` rows inside one episode, all usable at the start."""
        h = self.horizon if horizon is None else horizon
        candidates = rows[(self.step[rows] % h == 0)]
        end = candidates + h - 1
        ok = end < self.data.size
        candidates, end = candidates[ok], end[ok]
        return candidates[self.episode[end] == self.episode[candidates]]

    # --- channels -------------------------------------------------------------------------
    def applied_actions(self, hypothesis: Hypothesis) -> np.ndarray:
        """The commands after the declared and hypothesized action-channel effects (noise left out)."""
        effects = tuple(e for e in (*self.source.declared_channel_effects, *hypothesis)
                        if isinstance(e, ChannelEffect) and e.channel == "action" and not _is_stochastic(e))
        cached = self._actions_cache.get(effects)
        if cached is not None:
            return cached
        actions = np.array(self.data.actions, dtype=float)
        for effect in effects:
            mask = effect.dimension_mask(actions.shape[1], self.source.base_model)
            if effect.delay_steps:
                k = int(effect.steps)  # type: ignore[attr-defined]
                source_row = np.arange(len(actions)) - k
                valid = source_row >= self.episode_start_row
                shifted = np.where(valid[:, None], actions[np.maximum(source_row, 0)], 0.0)
                actions = np.where(mask, shifted, actions)
            else:
                actions = effect.transform(actions, mask, None)
        self._actions_cache[effects] = actions
        return actions

    def _states_for(self, hypothesis: Hypothesis) -> np.ndarray:
        if not self.rebuilt:
            return self.states
        biases = tuple(e for e in hypothesis if e.kind == "obs_bias")
        if not biases:
            return self.states
        cached = self._rebuilt_cache.get(biases)
        if cached is None:
            observations = np.array(self.data.observations, dtype=float)
            for effect in biases:
                observations[:, int(effect.target)] -= effect.value  # type: ignore[attr-defined, arg-type]
            qpos_qvel, _, _ = rebuild_states(self.source, observations)
            nq = self.source.base_model.nq
            cached = self.source.full_states(qpos_qvel[:, :nq], qpos_qvel[:, nq:])
            self._rebuilt_cache[biases] = cached
        return cached

    def _observe_state_rows(self, rows: np.ndarray, hypothesis: Hypothesis) -> np.ndarray:
        return self.source.observation_map.observe(self.source.qpos_qvel(self._states_for(hypothesis)[rows]))

    # --- prediction -----------------------------------------------------------------------
    def predict(self, hypotheses: Sequence[Hypothesis], starts: np.ndarray, horizon: int,
                cache_key: str | None = None, sensors: bool = True) -> list[np.ndarray]:
        """Predicted observations (mapped dimensions) ``horizon`` steps after each start row, for
        each hypothesis; hypotheses with the same physics share one rollout. ``sensors=False``
        reads the predicted state through the observation map only, without observation effects."""
        keys = [physics_key(h, self.rebuilt) for h in hypotheses]
        found: dict[tuple[Effect, ...], np.ndarray] = {}
        todo: dict[tuple[Effect, ...], Hypothesis] = {}
        for h, key in zip(hypotheses, keys):
            if cache_key is not None and (key, cache_key, horizon) in self._cache:
                found[key] = self._cache[(key, cache_key, horizon)]
            elif key not in todo:
                todo[key] = h
        if todo:
            offsets = np.arange(horizon)
            models, states, controls, jobs = [], [], [], []
            for key, h in todo.items():
                model_effects = tuple(e for e in key if isinstance(e, ModelEffect))
                state_key = tuple(e for e in key if e.kind == "obs_bias")
                model = self.source.model_with(model_effects)
                control = self.applied_actions(h)[starts[:, None] + offsets]
                # Rows whose model, start state and commands equal a rollout already done reuse it:
                # a dead zone or a delay changes only some rows' commands.
                reference, rows = None, np.arange(len(starts))
                for candidate in self._reference.get((model_effects, state_key, cache_key, horizon), []):
                    if candidate[0].shape == control.shape:
                        differ = np.flatnonzero(np.any(candidate[0] != control, axis=(1, 2)))
                        if len(differ) < len(rows):
                            reference, rows = candidate, differ
                jobs.append((key, model_effects, state_key, control, reference, rows))
                models.extend([model] * len(rows))
                states.append(self._states_for(h)[starts[rows]])
                controls.append(control[rows])
            total = sum(len(job[-1]) for job in jobs)
            result = (self.source.predict(models, np.concatenate(states), np.concatenate(controls))
                      if total else None)
            offset = 0
            for key, model_effects, state_key, control, reference, rows in jobs:
                if reference is None:
                    trajectory = np.empty((len(starts), horizon, self.source.qpos_qvel(self.source.reference_state).size))
                else:
                    trajectory = reference[1].copy()
                if len(rows):
                    trajectory[rows] = self.source.qpos_qvel(result[offset:offset + len(rows)])  # type: ignore[index]
                offset += len(rows)
                found[key] = trajectory
                if cache_key is not None:
                    # Keep the first rollout (usually the current hypothesis) and the latest few.
                    if len(self._reference) > 256:
                        self._reference.clear()
                    kept = self._reference.setdefault((model_effects, state_key, cache_key, horizon), [])
                    kept.append((control, trajectory))
                    if len(kept) > 6:
                        del kept[1]
                    if len(self._cache) > 64:
                        self._cache.clear()
                    self._cache[(key, cache_key, horizon)] = trajectory
        if not sensors:
            return [self.source.observation_map.observe(found[key][:, -1]) for key in keys]
        return [self._observation_channel(h, found[key], starts, horizon) for h, key in zip(hypotheses, keys)]

    def _observation_effects(self, hypothesis: Hypothesis) -> Iterator[tuple[Any, list[int]]]:
        """Each deterministic observation-channel effect (declared ones first) with the residual
        columns it acts on."""
        column = {int(d): c for c, d in enumerate(self.dims)}
        for effect in (*self.source.declared_channel_effects, *hypothesis):
            if getattr(effect, "channel", None) != "observation" or _is_stochastic(effect):
                continue
            mask = effect.dimension_mask(self.source.observation_size)
            yield effect, [column[d] for d in np.flatnonzero(mask) if d in column]

    def _observation_channel(self, hypothesis: Hypothesis, trajectory: np.ndarray, starts: np.ndarray,
                             horizon: int) -> np.ndarray:
        omap = self.source.observation_map
        predicted = omap.observe(trajectory[:, -1])
        for effect, columns in self._observation_effects(hypothesis):
            if effect.kind == "obs_bias":
                predicted[:, columns] += effect.value  # type: ignore[attr-defined]
            elif effect.kind == "obs_delay":
                # The recorded observation is the one from `steps` control steps earlier.
                back = horizon - int(effect.steps)  # type: ignore[attr-defined]
                if back >= 1:
                    delayed = omap.observe(trajectory[:, back - 1])
                else:
                    rows = np.maximum(starts + back, self.episode_start_row[starts])
                    delayed = self._observe_state_rows(rows, hypothesis)
                predicted[:, columns] = delayed[:, columns]
        return predicted

    def residuals(self, hypotheses: Sequence[Hypothesis], subset: str, horizon: int = 1) -> list[np.ndarray]:
        """Normalized residuals (prediction minus record) ``[rows, dims]`` for each hypothesis."""
        starts = self.subsets[subset] if horizon == 1 else self.windows[subset]
        if len(starts) == 0:
            return [np.zeros((0, self.dims.size)) for _ in hypotheses]
        recorded = self.data.next_observations[starts + horizon - 1][:, self.dims]
        spread = self.spread if horizon == 1 else self.horizon_spread
        predictions = self.predict(hypotheses, starts, horizon, cache_key=subset)
        return [(p - recorded) / spread for p in predictions]

    def search_residuals(self, hypotheses: Sequence[Hypothesis], subset: str) -> list[np.ndarray]:
        """Residuals the search works on: ``search_horizon`` steps open loop from the starts of
        ``subset`` (``screen``, ``fit``, ``train`` or ``heldout``); one step by default."""
        k = self.search_horizon
        if self.search_on_states:
            starts = self.search_starts[subset]
            recorded = self.state_reading(starts + k)
            predictions = self.predict(hypotheses, starts, k, cache_key=f"search-{subset}", sensors=False)
            return [(p - recorded) / self.search_spread for p in predictions]
        if k == 1:
            return self.residuals(hypotheses, subset)
        starts = self.search_starts[subset]
        recorded = self.data.next_observations[starts + k - 1][:, self.dims]
        predictions = self.predict(hypotheses, starts, k, cache_key=f"search-{subset}")
        return [(p - recorded) / self.search_spread for p in predictions]

    def search_floor(self) -> tuple[float, np.ndarray]:
        """The noise floor in the search's units: the endpoint's sensor noise over the spread of the
        ``search_horizon``-step change (the start state is the stored one, exact). Searching on
        the stored states, no sensor is involved: the floor is the numerical one."""
        if self.search_on_states:
            return NUMERICAL_FLOOR, np.full(self.dims.size, NUMERICAL_FLOOR)
        floor, per_dim = self.noise_floor()
        if self.search_horizon == 1:
            return floor, per_dim
        scaled = np.maximum(per_dim * self.spread / self.search_spread, NUMERICAL_FLOOR)
        return max(float(np.sqrt(np.mean(scaled**2))), NUMERICAL_FLOOR), scaled

    def summary(self, hypothesis: Hypothesis) -> dict[str, ErrorSummary]:
        """One-step error on training and held-out rows, and H-step error on all windows. The
        H-step entries are left out where no window of ``horizon`` steps exists: not measured."""
        train, = self.residuals([hypothesis], "train")
        heldout, = self.residuals([hypothesis], "heldout")
        h_train, = self.residuals([hypothesis], "train", self.horizon)
        h_heldout, = self.residuals([hypothesis], "heldout", self.horizon)
        out = {"train": ErrorSummary.of(train), "heldout": ErrorSummary.of(heldout)}
        if len(h_train) + len(h_heldout):
            out["horizon"] = ErrorSummary.of(np.concatenate([h_train, h_heldout]))
        if len(h_heldout):
            out["horizon_heldout"] = ErrorSummary.of(h_heldout)
        return out

    # --- the observation channel and the noise floor, from the data alone ----------------------
    def _discrepancy(self, rows: np.ndarray, shift: int = 0) -> np.ndarray:
        """Recorded observation minus the one read off the stored state ``shift`` control steps
        earlier (clamped to the episode start), normalized like the residual."""
        back = np.maximum(rows - shift, self.episode_start_row[rows])
        read = self.source.observation_map.observe(self.source.qpos_qvel(self.states[back]))
        return (self.data.observations[rows][:, self.dims] - read) / self.spread

    def _check_observation_channel(self) -> ObservationCheck:
        """Which observation effects the data allow on each dimension, and the noise floor.

        With stored states the recorded observation can be compared with the one the state
        implies, with no model involved. A dimension whose two readings agree to numerical
        precision admits no observation effect at all; a bias is a candidate only where the
        discrepancy has a mean (tested across episodes), a delay only where reading an earlier
        state removes significantly more of it than chance would. The floor is the spread of the discrepancy that is left: a
        measurement of the sensors, fixed before any hypothesis is judged, so no hypothesis can
        move it. Without stored states, observation and state cannot be told apart: every
        observation bias stays a candidate, delays are not (the rebuilt state carries the delay),
        and the floor is the numerical one.
        """
        mapped = [int(d) for d in self.dims]
        if self.rebuilt:
            return ObservationCheck(max_discrepancy=None, bias_allowed=tuple(mapped), delay_allowed=(),
                                    floor_per_dimension=np.full(self.dims.size, NUMERICAL_FLOOR), floor_source=(
                                        "numerical: without stored states sensor noise cannot be told apart from "
                                        "model error"))
        rows = np.flatnonzero(self.usable)
        now = self._discrepancy(rows)
        rms_now = np.sqrt(np.mean(now**2, axis=0))
        # Spreads, not RMS: a constant bias is no delay, whatever a shift does to the mean.
        shifted = [np.std(self._discrepancy(rows, s), axis=0) for s in DELAY_SHIFTS]
        centred = np.std(now, axis=0)
        floor = centred.copy()
        bias, delay = [], []
        delay_steps: dict[int, int] = {}
        bias_values: dict[int, tuple[float, float]] = {}
        episodes = self.episode[rows]
        for c, d in enumerate(mapped):
            if rms_now[c] <= AGREEMENT_TOLERANCE:
                continue  # the sensor reads the state exactly: nothing to explain
            best_shift = min(range(len(DELAY_SHIFTS)), key=lambda i: shifted[i][c])
            # Reading an earlier state must remove more of the difference than chance would: with
            # noisy sensors a delay removes only the state's change over a step, a small part.
            late = shifted[best_shift][c] < centred[c] * (1.0 - 3.0 / np.sqrt(len(rows)))
            if late:
                delay.append(d)
                delay_steps[d] = DELAY_SHIFTS[best_shift]
                floor[c] = shifted[best_shift][c]
            # An offset is read against the state the sensor really reports (the delayed one):
            # against the current state, a late sensor's difference carries the state's change.
            aligned = self._discrepancy(rows, delay_steps[d])[:, c] if late else now[:, c]
            if _mean_is_significant(aligned, episodes):
                bias.append(d)
                offset = aligned * self.spread[c]
                bias_values[d] = (float(offset.mean()), _episode_standard_error(offset, episodes))
        floor = np.maximum(floor, NUMERICAL_FLOOR)
        return ObservationCheck(max_discrepancy=float(np.max(np.abs(now))) if now.size else 0.0,
                                bias_allowed=tuple(bias), delay_allowed=tuple(delay), floor_per_dimension=floor,
                                floor_source="measured: the recorded observations against the stored states",
                                delay_steps=delay_steps, bias_values=bias_values)

    def noise_floor(self) -> tuple[float, np.ndarray]:
        """Normalized one-step error a perfect model would still make, and its per-dimension part:
        measured once from the data (see :meth:`_check_observation_channel`), the same for every
        hypothesis."""
        per_dim = self.observation_check.floor_per_dimension
        return max(float(np.sqrt(np.mean(per_dim**2))), NUMERICAL_FLOOR), per_dim


@dataclasses.dataclass(frozen=True)
class ObservationCheck:
    """What the stored states say about the observation channel."""

    max_discrepancy: float | None
    """Largest normalized difference between a recorded observation and the one its stored state
    implies; ``None`` without stored states."""
    bias_allowed: tuple[int, ...]
    """Observation indices where an ``obs_bias`` is a candidate."""
    delay_allowed: tuple[int, ...]
    """Observation indices where an ``obs_delay`` is a candidate."""
    floor_per_dimension: np.ndarray
    floor_source: str
    delay_steps: dict[int, int] = dataclasses.field(default_factory=dict)
    """Per observation index with a delay: the control steps the sensor lags the stored state."""
    bias_values: dict[int, tuple[float, float]] = dataclasses.field(default_factory=dict)
    """Per observation index with a bias: the offset (observation units) and its standard error
    across episodes, measured against the state the sensor reports."""

    @property
    def sensors_differ(self) -> bool:
        """Whether some recorded observation differs from the one its stored state implies."""
        return self.max_discrepancy is not None and self.max_discrepancy > AGREEMENT_TOLERANCE

    def note(self, names: Sequence[str]) -> str | None:
        if self.max_discrepancy is None:
            return None
        if not self.bias_allowed and not self.delay_allowed:
            if self.max_discrepancy <= AGREEMENT_TOLERANCE:
                return (f"the recorded observations equal those read off the stored states (largest difference "
                        f"{self.max_discrepancy:.2g}, normalized): no observation effect is a candidate")
            return ("the recorded observations differ from the stored states only by zero-mean noise that no "
                    "time shift removes: no observation effect is a candidate; the noise sets the floor")
        allowed = [f"bias on {names[d]}" for d in self.bias_allowed] + [f"delay on {names[d]}" for d in self.delay_allowed]
        return "the stored states show an observation-channel discrepancy; candidates: " + ", ".join(allowed)


# A time shift of the recorded observation of up to this many control steps is looked for.
DELAY_SHIFTS = (1, 2)
# A sensor whose normalized RMS difference from the stored state is below this reads it exactly.
AGREEMENT_TOLERANCE = 1e-6


def _mean_is_significant(values: np.ndarray, episodes: np.ndarray) -> bool:
    """Is the mean of ``values`` non-zero beyond chance? Episodes are the independent units
    (neighbouring rows are correlated); with one episode, blocks of 50 rows stand in for them."""
    means = _unit_means(values, episodes)
    se = means.std(ddof=1) / np.sqrt(len(means))
    return abs(float(means.mean())) > 4.0 * se + 1e-6


def _unit_means(values: np.ndarray, episodes: np.ndarray) -> np.ndarray:
    """Means of ``values`` per independent unit: per episode, or per block of 50 rows with fewer
    than three episodes (neighbouring rows are correlated)."""
    groups = np.unique(episodes)
    if len(groups) >= 3:
        return np.array([values[episodes == g].mean() for g in groups])
    return np.array([chunk.mean() for chunk in np.array_split(values, max(2, len(values) // 50))])


def _episode_standard_error(values: np.ndarray, episodes: np.ndarray) -> float:
    """Standard error of the mean of ``values``, the units counted as :func:`_unit_means` does."""
    means = _unit_means(values, episodes)
    return float(means.std(ddof=1) / np.sqrt(len(means)))


def _safe_spread(change: np.ndarray) -> np.ndarray:
    spread = np.std(change, axis=0) if len(change) > 1 else np.ones(change.shape[1])
    return np.where(spread > 1e-12, spread, 1.0)


def block_improvement_z(before: np.ndarray, after: np.ndarray, block: int = 50) -> float:
    """How significant the drop of per-row squared error is, in standard-normal units.

    Neighbouring rows are correlated, so rows are summed in blocks of consecutive rows (at most
    ``block`` long, at least 20 blocks when the data allow). Two tests, and the stronger counts:
    the z of the mean block gain (sensitive to a uniform gain), and a sign test over blocks
    (robust when the gain sits in a few blocks with heavy tails).
    """
    from scipy import stats

    diff = np.sum(before**2, axis=1) - np.sum(after**2, axis=1)
    size = int(np.clip(len(diff) // 20, 5, block))
    n_blocks = max(1, len(diff) // size)
    sums = np.array([chunk.mean() for chunk in np.array_split(diff, n_blocks)])
    if len(sums) < 2:
        return float("inf") if sums.mean() > 0 else 0.0
    se = sums.std(ddof=1) / np.sqrt(len(sums))
    z_mean = (float("inf") if sums.mean() > 0 else 0.0) if se == 0 else float(sums.mean() / se)
    improved = int(np.sum(sums > 0))
    p_sign = stats.binomtest(improved, len(sums), 0.5, alternative="greater").pvalue
    z_sign = float(stats.norm.isf(max(p_sign, 1e-300)))
    return max(z_mean, z_sign)
