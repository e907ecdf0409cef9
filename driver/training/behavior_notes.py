"""What a behavior's settings mean for it, said once as the run meets it: the defaults
when the config does not name it (in mlagents-learn's words), blank cameras when the build
runs without graphics, and group rewards that its trainer does not train on; and the
learner's own notes (mixed precision it cannot use), said once in the driver's log."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

from batches.contracts import base_name
from driver.declaration import TrainingError
from learners.trainer_config.parse import DEFAULTS
from learners.trainer_config.settings import RunConfig

log = logging.getLogger(__name__)


class BehaviorNotes:
    """Says, once per behavior, what its settings mean for it: the defaults, when the
    config does not name it (in mlagents-learn's words); blank cameras, when the build
    runs without graphics; group rewards its trainer does not train on."""

    def __init__(self, config: RunConfig, no_graphics: bool) -> None:
        self.config, self.no_graphics = config, no_graphics
        self.seen, self.named = set[str](), set[str]()  # behaviors, and their config names
        self.said = set[str]()  # the learner's notes

    def learner(self, notes: list[str]) -> None:
        """The learner's notes (``CentralLearner.progress``), each said once: a restored
        learner repeats them."""
        for note in notes:
            if note not in self.said:
                self.said.add(note)
                log.warning("%s", note)

    def _unconfigured(self, name: str) -> None:
        """As mlagents-learn: without a file, the defaults and a warning; with one, its
        default_settings, else a stop naming what to add."""
        source = self.config.source
        if source == DEFAULTS:
            log.warning(
                "Behavior name %s does not match any behaviors specified in the trainer "
                "configuration file. A default configuration will be used.",
                name,
            )
        elif self.config.default_given:
            log.warning(
                "%s is not among the behaviors of %s: it trains with default_settings",
                name,
                source,
            )
        else:
            raise TrainingError(
                f"the build's behavior {name} is not in {source}: add it under behaviors:, or "
                "add a default_settings: section (mlagents-learn stops here too)"
            )

    def report(self, specs: Mapping[str, dict[str, Any]]) -> None:
        for behavior, spec in specs.items():
            if behavior in self.seen:
                continue
            self.seen.add(behavior)
            name = base_name(behavior)
            if name not in self.config.behaviors and name not in self.named:
                self.named.add(name)
                self._unconfigured(name)
            images = [o["name"] for o in spec["observations"] if len(o["shape"]) == 3]
            if self.no_graphics and images:
                log.warning(
                    "%s observes images (%s) and the build runs without graphics "
                    "(engine_settings.no_graphics or --no-graphics): its cameras send blank "
                    "frames (grid sensors are not rendered and stay as they are)",
                    behavior,
                    ", ".join(images),
                )
