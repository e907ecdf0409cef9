"""Each transition's groupmates, as ML-Agents' agent processor records them for POCA.

An agent with a ``group_id`` above 0 belongs to a multi-agent group (one per group id
and worker). Every transition of such an agent carries the *status* of each other member
of its group: the observation that member acted on, its action, the reward and the done
flag of its own latest report, and its newest observation (for the bootstrap where the
trajectory ends). A member's status is set whenever it reports with an action pending,
persists while it does not report, and is forgotten after the exchange in which its
episode ends: so an agent that leaves the group mid-episode (DungeonEscape's sacrifice)
is in the statuses of that exchange, with ``done``, and not after. Within an exchange,
as in ML-Agents, the terminal reports set their statuses first and complete their
transitions, then the decision reports do the same.

Storage is per builder slot (the agent) and per row ``(slots, horizon, M, ...)``, ``M``
the most groupmates seen so far; it grows, never shrinks, and absent members are zeros
with ``present`` False. A behavior without groups keeps ``M = 0``: nothing to carry.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from batches import keys


class Groupmates:
    """Statuses per slot, and the groupmates of each recorded transition per row."""

    def __init__(
        self,
        sensors: Sequence[tuple[str, tuple[int, ...], type]],
        continuous: int,
        branches: int,
        slots: int,
        horizon: int,
    ) -> None:
        self._sensors = list(sensors)  # (name, shape, stored dtype)
        self._continuous, self._branches = continuous, branches
        self._horizon = horizon
        self.capacity = 0  # M: groupmate places per transition
        self._status = self._status_fields(slots)
        self._rows = self._row_fields(slots, 0)

    # --- storage ------------------------------------------------------------------------

    def _status_fields(self, s: int) -> dict[str, np.ndarray]:
        fields = {
            "valid": np.zeros(s, np.bool_),
            "group": np.zeros(s, np.int64),
            "cont": np.zeros((s, self._continuous), np.float32),
            "disc": np.zeros((s, self._branches), np.int64),
            "reward": np.zeros(s, np.float32),
            "done": np.zeros(s, np.bool_),
        }
        for name, shape, dtype in self._sensors:
            fields[f"obs/{name}"] = np.zeros((s, *shape), dtype)
            fields[f"now/{name}"] = np.zeros((s, *shape), dtype)
        return fields

    def _row_fields(self, s: int, m: int) -> dict[str, np.ndarray]:
        t = self._horizon
        fields = {
            "present": np.zeros((s, t, m), np.bool_),
            "cont": np.zeros((s, t, m, self._continuous), np.float32),
            "disc": np.zeros((s, t, m, self._branches), np.int64),
            "reward": np.zeros((s, t, m), np.float32),
            "done": np.zeros((s, t, m), np.bool_),
        }
        for name, shape, dtype in self._sensors:
            fields[f"obs/{name}"] = np.zeros((s, t, m, *shape), dtype)
            fields[f"next/{name}"] = np.zeros((s, t, m, *shape), dtype)
        return fields

    def resize(self, slots: int) -> None:
        """The builder grew to ``slots`` agents: keep what is there."""
        old_status, old_rows = self._status, self._rows
        self._status = self._status_fields(slots)
        self._rows = self._row_fields(slots, self.capacity)
        for new, old in ((self._status, old_status), (self._rows, old_rows)):
            for name, array in old.items():
                new[name][: len(array)] = array

    def _widen(self, m: int) -> None:
        old = self._rows
        self._rows = self._row_fields(len(self._status["valid"]), m)
        for name, array in old.items():
            self._rows[name][:, :, : self.capacity] = array
        self.capacity = m

    # --- one exchange -------------------------------------------------------------------

    def set_status(
        self,
        slots: np.ndarray,
        group: np.ndarray,
        acted_obs: Sequence[np.ndarray],
        continuous: np.ndarray,
        discrete: np.ndarray,
        obs: Sequence[np.ndarray],
        reward: np.ndarray,
        done: np.ndarray,
    ) -> None:
        """Agents that reported with an action pending: what they acted on and did, and
        what they see now. Agents outside any group (group 0) get no status."""
        grouped = group > 0
        slots, st = slots[grouped], self._status
        if not len(slots):
            return
        st["valid"][slots], st["group"][slots] = True, group[grouped]
        st["cont"][slots], st["disc"][slots] = continuous[grouped], discrete[grouped]
        st["reward"][slots], st["done"][slots] = reward[grouped], done[grouped]
        for (name, _, _), before, now in zip(self._sensors, acted_obs, obs, strict=True):
            st[f"obs/{name}"][slots] = before[grouped]
            st[f"now/{name}"][slots] = now[grouped]

    def record(
        self, slots: np.ndarray, time: np.ndarray, group: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The groupmates of transitions just completed at row positions ``time``: every
        other agent of the same group that has a status (the other places empty).
        Returns, per transition, whether a groupmate's episode goes on, and the sum of the
        groupmates' rewards (POCA's extrinsic reward adds it)."""
        going_on, rewards = np.zeros(len(slots), np.bool_), np.zeros(len(slots), np.float32)
        if not len(slots):
            return going_on, rewards
        st = self._status
        members = np.flatnonzero(st["valid"])
        mate = (
            (group[:, None] > 0)
            & (st["group"][members][None, :] == group[:, None])
            & (members[None, :] != slots[:, None])
        )
        count = int(mate.sum(1).max()) if len(members) else 0
        if count > self.capacity:
            self._widen(count)
        m = self.capacity
        if m == 0:
            return going_on, rewards
        if len(members) < m:  # fewer candidates than places: pad with empty ones
            members = np.pad(members, (0, m - len(members)))
            mate = np.pad(mate, ((0, 0), (0, m - mate.shape[1])))
        order = np.argsort(~mate, axis=1, kind="stable")[:, :m]
        present = np.take_along_axis(mate, order, axis=1)
        mates = members[order]  # (n, m) slots, meaningful where present
        rows, t, place = slots[:, None], time[:, None], np.arange(m)[None, :]

        def put(row_field: str, status_field: str) -> None:
            values = st[status_field][mates]
            shaped = present.reshape(*present.shape, *([1] * (values.ndim - 2)))
            self._rows[row_field][rows, t, place] = np.where(shaped, values, 0)

        self._rows["present"][rows, t, place] = present
        for field in ("cont", "disc", "reward", "done"):
            put(field, field)
        for name, _, _ in self._sensors:
            put(f"obs/{name}", f"obs/{name}")
            put(f"next/{name}", f"now/{name}")
        rewards = self._rows["reward"][slots, time].sum(1)  # absent places hold 0
        return (present & ~st["done"][mates]).any(1), rewards

    def forget(self, slots: np.ndarray) -> None:
        """Agents whose episode ended (after the exchange), or whose slot was freed."""
        self._status["valid"][slots] = False

    # --- out ----------------------------------------------------------------------------

    def take(self, row_of: np.ndarray, time: np.ndarray) -> tuple[dict, dict]:
        """The packed steps' groupmates: ``(under the step, under "next")``, each
        ``[N, M, ...]``, keyed as docs/batch-format.md has them."""
        r = self._rows

        def pick(name: str) -> np.ndarray:
            return r[name][row_of, time]

        action = {}
        if self._continuous:
            action[keys.CONTINUOUS] = pick("cont")
        if self._branches:
            action[keys.DISCRETE] = pick("disc")
        here = {
            keys.OBS: {name: pick(f"obs/{name}") for name, _, _ in self._sensors},
            keys.ACTION: action,
            keys.REWARD: pick("reward"),
            keys.DONE: pick("done"),
            keys.PRESENT: pick("present"),
        }
        after = {keys.OBS: {name: pick(f"next/{name}") for name, _, _ in self._sensors}}
        return here, after
