"""Match3: swap neighbouring pieces to make lines of three (ML-Agents example, batched).

Laid out as ML-Agents' ``Match3`` scene (release 21): twelve boards, one agent each, every
board a ``Match3Board`` of at most 9 rows and 8 columns, 6 cell types and 2 special types.
The boards' agents carry four behaviors: ``Match3VectorObs`` (four boards, the board as
vectors), ``Match3VisualObs`` (four, the board as PNG-compressed images),
``Match3SimpleHeuristic`` and ``Match3SmartHeuristic`` (two each, vectors, their actuator's
``ForceHeuristic`` set: they play a random valid move and the move worth the most points,
whatever action Python sends).

Each episode begins with a board of ``uniform(6..9)`` rows and ``uniform(6..8)`` columns,
filled at random and settled (matches cleared and refilled until none is left, no reward).
A move swaps a cell with its right or upper neighbour; the one action branch has
``Move.NumPotentialMoves`` = 9 * 7 + 8 * 8 = 127 values (the right swaps row by row, then the
up swaps), and every move that leaves the current board or makes no line is masked, as
``Match3Actuator.WriteDiscreteActionMask``. After a move, lines of three or more of one cell
type are cleared, the pieces above drop (towards row 0) and new ones fall in, again and again
until nothing matches; every cleared piece gives 0.01 times its points (1 for a basic piece,
2 and 3 for the special types). A board left without a valid move is dealt again. An agent
asks for a decision after every move and its episode is interrupted at 500 moves (MaxMoves).
New pieces are special with probability 2/10 (type 1) and 1/10 (type 2).

Sensors, sorted by name as Unity sorts them: ``Match3 Sensor (cells)``, a one-hot of each
cell's type (6 values), and ``Match3 Sensor (special)``, a one-hot of its special type
(3 values); rows then columns then values for the vector behaviors (432 and 216 floats),
(channels, rows, columns) images for the visual one, sent as 2 and 1 concatenated RGB PNGs as
``Match3Sensor.GetCompressedObservation`` does; cells outside the current board are zeros.

Simplified: moves happen at once (the scene's animation runs only without a trainer), and
an episode's last decision is reported done in the message of its 500th move, followed by
the next episode's first decision.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping

import numpy as np

from unitysim.envs.base import Actions, AgentInfos, Behavior, Output, Parameters, Sensor, SimEnv

ROWS, COLUMNS = 9, 8
MIN_ROWS, MIN_COLUMNS = 6, 6
CELL_TYPES, SPECIAL_TYPES = 6, 3  # NumCellTypes 6; NumSpecialTypes 2, plus "not special"
POINTS = np.array([1, 2, 3], dtype=np.int64)  # Basic, SpecialCell1, SpecialCell2 points
REWARD_PER_POINT = 0.01
MAX_MOVES = 500
EMPTY = -1
RIGHT_MOVES = ROWS * (COLUMNS - 1)
MOVES = RIGHT_MOVES + (ROWS - 1) * COLUMNS  # 127

# every move's two cells (row, column), in Move.FromMoveIndex order
_index = np.arange(MOVES)
_right = _index < RIGHT_MOVES
_up_offset = _index - RIGHT_MOVES
MOVE_ROW = np.where(_right, _index // (COLUMNS - 1), _up_offset // COLUMNS)
MOVE_COLUMN = np.where(_right, _index % (COLUMNS - 1), _up_offset % COLUMNS)
OTHER_ROW = MOVE_ROW + ~_right
OTHER_COLUMN = MOVE_COLUMN + _right
MOVE_CELL, OTHER_CELL = MOVE_ROW * COLUMNS + MOVE_COLUMN, OTHER_ROW * COLUMNS + OTHER_COLUMN


def _lines_through_swaps() -> np.ndarray:
    """(MOVES, 12, 3): for every move, the 12 lines of three cells through its two cells (a
    line off the board names cell ROWS * COLUMNS, an empty one), each cell named by where its
    piece comes from once the move is made."""
    lines = np.full((MOVES, 12, 3), ROWS * COLUMNS, dtype=np.int64)
    for m in range(MOVES):
        ends = ((MOVE_ROW[m], MOVE_COLUMN[m]), (OTHER_ROW[m], OTHER_COLUMN[m]))
        source = {ends[0]: ends[1], ends[1]: ends[0]}
        k = 0
        for r, c in ends:
            for dr, dc in ((0, 1), (1, 0)):
                for start in (-2, -1, 0):
                    cells = [(r + (start + i) * dr, c + (start + i) * dc) for i in range(3)]
                    if all(0 <= y < ROWS and 0 <= x < COLUMNS for y, x in cells):
                        lines[m, k] = [
                            source.get((y, x), (y, x))[0] * COLUMNS + source.get((y, x), (y, x))[1]
                            for y, x in cells
                        ]
                    k += 1
    return lines


LINES = _lines_through_swaps()

# name, boards in the scene, plays its own heuristic (None: Python's actions), visual
KINDS = (
    ("Match3SimpleHeuristic", 2, "random", False),
    ("Match3SmartHeuristic", 2, "greedy", False),
    ("Match3VectorObs", 4, None, False),
    ("Match3VisualObs", 4, None, True),
)


def _sensors(visual: bool) -> tuple[Sensor, ...]:
    if visual:
        return (
            Sensor.visual("Match3 Sensor (cells)", CELL_TYPES, ROWS, COLUMNS),
            Sensor.visual("Match3 Sensor (special)", SPECIAL_TYPES, ROWS, COLUMNS),
        )
    return (
        Sensor.vector("Match3 Sensor (cells)", ROWS * COLUMNS * CELL_TYPES),
        Sensor.vector("Match3 Sensor (special)", ROWS * COLUMNS * SPECIAL_TYPES),
    )


def matched(cells: np.ndarray) -> np.ndarray:
    """(n, R, C) bool: the cells in a line of three or more of one type (empty cells and the
    outside of a board, negative, never match)."""
    real = cells >= 0
    found = np.zeros(cells.shape, dtype=bool)
    across = real[:, :, :-2] & (cells[:, :, :-2] == cells[:, :, 1:-1])
    across &= cells[:, :, 1:-1] == cells[:, :, 2:]
    down = real[:, :-2] & (cells[:, :-2] == cells[:, 1:-1]) & (cells[:, 1:-1] == cells[:, 2:])
    for shift in range(3):
        found[:, :, shift : COLUMNS - 2 + shift] |= across
        found[:, shift : ROWS - 2 + shift] |= down
    return found


class Match3(SimEnv):
    name = "Match3"
    behaviors = tuple(
        Behavior(f"{name}?team=0", _sensors(visual), branches=(MOVES,))
        for name, _, _, visual in KINDS
    )

    def __init__(self, rng: np.random.Generator, num_areas: int, params: Parameters) -> None:
        super().__init__(rng, num_areas, params)
        boards = [count for _, count, _, _ in KINDS]
        per_area = sum(boards)
        self.n = per_area * self.num_areas
        self.ids = np.arange(self.n, dtype=np.int32)  # area by area, as the scene's copies
        areas = per_area * np.arange(self.num_areas)[:, None]
        self.rows_of = [
            (areas + np.arange(start, end)).reshape(-1)
            for start, end in itertools.pairwise(np.cumsum([0, *boards]))
        ]
        self.cells = np.zeros((self.n, ROWS, COLUMNS), dtype=np.int64)  # type; < 0 outside
        self.special = np.zeros((self.n, ROWS, COLUMNS), dtype=np.int64)
        self.height = np.full(self.n, ROWS, dtype=np.int64)  # the current board size
        self.width = np.full(self.n, COLUMNS, dtype=np.int64)
        self.moves_made = np.zeros(self.n, dtype=np.int64)
        self.valid_moves = np.zeros((self.n, MOVES), dtype=bool)  # on the boards as reported
        # a distinct negative value per outside cell: the outside never matches itself
        self._outside_value = -2 - np.arange(ROWS * COLUMNS).reshape(ROWS, COLUMNS)

    # --- the board -----------------------------------------------------------------------

    def _inside(self, rows: np.ndarray) -> np.ndarray:
        r, c = np.arange(ROWS), np.arange(COLUMNS)
        return (r[None, :, None] < self.height[rows, None, None]) & (
            c[None, None, :] < self.width[rows, None, None]
        )

    def _fill(self, rows: np.ndarray, where: np.ndarray) -> None:
        """New random pieces at ``where`` ((k, R, C) bool) of the boards ``rows``."""
        k = int(where.sum())
        cells, special = self.cells[rows], self.special[rows]
        cells[where] = self.rng.integers(0, CELL_TYPES, k)
        draw = self.rng.integers(0, 10, k)  # 1 in 10: type 2, 2 in 10: type 1
        special[where] = np.where(draw == 0, 2, np.where(draw <= 2, 1, 0))
        self.cells[rows], self.special[rows] = cells, special

    def _settle(self, rows: np.ndarray) -> np.ndarray:
        """Clear lines, drop, refill until nothing matches; the points each board earned."""
        points = np.zeros(len(rows), dtype=np.int64)
        place = np.arange(len(rows))  # where each board still settling is in ``rows``
        while len(place):
            cells, special = self.cells[rows[place]], self.special[rows[place]]
            found = matched(cells)
            going = found.any(axis=(1, 2))
            if not going.any():
                break
            place, cells, special, found = place[going], cells[going], special[going], found[going]
            points[place] += (POINTS[special] * found).sum((1, 2))
            boards = rows[place]
            cells[found] = EMPTY
            # gravity towards row 0 inside the board: pieces, then the empties, then outside
            key = np.where(cells == EMPTY, 1, np.where(cells < 0, 2, 0))
            order = np.argsort(key, axis=1, kind="stable")
            self.cells[boards] = np.take_along_axis(cells, order, axis=1)
            self.special[boards] = np.take_along_axis(special, order, axis=1)
            self._fill(boards, self.cells[boards] == EMPTY)
        return points

    def _deal(self, rows: np.ndarray) -> None:
        """``InitSettled`` on the boards ``rows``: random pieces, settled without reward."""
        inside = self._inside(rows)
        self.cells[rows] = np.where(inside, 0, self._outside_value)
        self._fill(rows, inside)
        self._settle(rows)

    def _valid(self, rows: np.ndarray) -> np.ndarray:
        """(k, MOVES) bool: the moves inside the board that make a line. On a settled board a
        line after a swap runs through a swapped cell, so only those lines are looked at."""
        cells = self.cells[rows].reshape(len(rows), -1)
        a, b = cells[:, MOVE_CELL], cells[:, OTHER_CELL]
        in_range = (OTHER_ROW[None] < self.height[rows, None]) & (
            OTHER_COLUMN[None] < self.width[rows, None]
        )
        line = np.take(np.append(cells, np.full((len(rows), 1), EMPTY), 1), LINES, axis=1)
        three = (
            (line[..., 0] >= 0) & (line[..., 0] == line[..., 1]) & (line[..., 1] == line[..., 2])
        )
        return in_range & (a != b) & three.any(-1)

    def _swapped(self, boards: np.ndarray, move: np.ndarray) -> np.ndarray:
        out = boards.copy()
        i = np.arange(len(move))
        r, c, r2, c2 = MOVE_ROW[move], MOVE_COLUMN[move], OTHER_ROW[move], OTHER_COLUMN[move]
        out[i, r, c], out[i, r2, c2] = boards[i, r2, c2], boards[i, r, c]
        return out

    def _playable(self, rows: np.ndarray) -> np.ndarray:
        """Deal again every board of ``rows`` left without a valid move; their valid moves."""
        valid = self._valid(rows)
        while (stuck := ~valid.any(1)).any():
            self._deal(rows[stuck])
            valid[stuck] = self._valid(rows[stuck])
        return valid

    def _greedy(self, rows: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """The valid move whose lines are worth the most points (ties: uniformly)."""
        board, move = np.nonzero(valid)
        cells = self._swapped(self.cells[rows][board], move)
        special = self._swapped(self.special[rows][board], move)
        worth = np.full(valid.shape, -1.0)
        worth[board, move] = (POINTS[special] * matched(cells)).sum((1, 2))
        worth += self.rng.random(worth.shape) * 0.5 * valid  # a uniform pick among the best
        return worth.argmax(1)

    # --- the contract --------------------------------------------------------------------

    def _begin(self, rows: np.ndarray) -> None:
        self.height[rows] = self.rng.integers(MIN_ROWS, ROWS + 1, len(rows))
        self.width[rows] = self.rng.integers(MIN_COLUMNS, COLUMNS + 1, len(rows))
        self._deal(rows)
        self.moves_made[rows] = 0

    def _observe(self, rows: np.ndarray, visual: bool) -> list[np.ndarray]:
        inside = self._inside(rows)
        out = []
        for values, size in ((self.cells[rows], CELL_TYPES), (self.special[rows], SPECIAL_TYPES)):
            hot = (values[..., None] == np.arange(size)) & inside[..., None]  # (k, R, C, size)
            hot = hot.astype(np.float32)
            out.append(hot.transpose(0, 3, 1, 2) if visual else hot.reshape(len(rows), -1))
        return out

    def _report(self, reward: np.ndarray, terminal: Output) -> Output:
        """Every board's decision (after the terminal infos of the episodes that ended)."""
        self.valid_moves = self._playable(self.ids)  # what the next step's moves may be
        masks = ~self.valid_moves
        out: Output = {}
        for behavior, rows, (_, _, _, visual) in zip(
            self.behaviors, self.rows_of, KINDS, strict=True
        ):
            decisions = AgentInfos.build(
                self.ids[rows], self._observe(rows, visual), reward[rows], action_mask=masks[rows]
            )
            ended = terminal.get(behavior.name)
            out[behavior.name] = (
                decisions if ended is None else AgentInfos.concat([ended, decisions])
            )
        return out

    def _terminal(self, ended: np.ndarray, reward: np.ndarray) -> Output:
        out: Output = {}
        for behavior, rows, (_, _, _, visual) in zip(
            self.behaviors, self.rows_of, KINDS, strict=True
        ):
            over = rows[ended[rows]]
            if len(over):
                out[behavior.name] = AgentInfos.build(
                    self.ids[over],
                    self._observe(over, visual),
                    reward[over],
                    done=True,
                    max_step_reached=True,
                    action_mask=~self._valid(over),
                )
        return out

    def reset(self) -> Output:
        self._begin(self.ids)
        return self._report(np.zeros(self.n), {})

    def step(self, actions: Mapping[str, Actions]) -> Output:
        move = np.full(self.n, -1, dtype=np.int64)
        valid = self.valid_moves
        for behavior, rows, (_, _, heuristic, _) in zip(
            self.behaviors, self.rows_of, KINDS, strict=True
        ):
            if heuristic == "greedy":
                move[rows] = self._greedy(rows, valid[rows])
            elif heuristic == "random":
                move[rows] = (self.rng.random(valid[rows].shape) * valid[rows]).argmax(1)
            elif behavior.name in actions and len(actions[behavior.name]):
                move[rows] = np.clip(actions[behavior.name].discrete[:, 0], 0, MOVES - 1)
        made = (move >= 0) & valid[self.ids, np.maximum(move, 0)]  # an invalid move: nothing
        rows = self.ids[made]
        self.cells[rows] = self._swapped(self.cells[rows], move[made])
        self.special[rows] = self._swapped(self.special[rows], move[made])
        reward = np.zeros(self.n)
        reward[rows] = REWARD_PER_POINT * self._settle(rows)
        self.moves_made += 1
        ended = self.moves_made >= MAX_MOVES
        terminal = self._terminal(ended, reward)
        if ended.any():
            self._begin(self.ids[ended])
            reward[ended] = 0.0
        return self._report(reward, terminal)
