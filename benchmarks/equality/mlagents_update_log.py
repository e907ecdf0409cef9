"""Run the anchor's mlagents-learn launcher with each on-policy update's size written down.

    UPDATE_LOG=<file> <anchor>/venv/bin/python benchmarks/equality/mlagents_update_log.py \\
        <anchor>/mlagents_learn_launcher.py <mlagents-learn arguments>

Each line is ``[step, steps in the buffer, brain]``, read as ``OnPolicyTrainer._update_policy``
starts: what mlagents-learn 1.1.0 trains on in that update. Nothing in site-packages is
edited: the method is wrapped at run time (``mlagents_hooks.py``). Run by the anchor's own
Python as a plain file (by its path, not ``-m``): it imports nothing of ours but
``mlagents_hooks.py`` beside it.
"""

from __future__ import annotations

import json
import os
import sys
from typing import Any

if __package__:  # imported as benchmarks.equality.mlagents_update_log
    from benchmarks.equality.mlagents_hooks import run_patched
else:  # run as a file by the anchor's Python: this folder is sys.path[0]
    from mlagents_hooks import run_patched


def wrap() -> None:
    from mlagents.trainers.trainer import on_policy_trainer

    trainer = on_policy_trainer.OnPolicyTrainer
    update = trainer._update_policy
    log = os.environ["UPDATE_LOG"]

    def logged(self: Any) -> Any:
        with open(log, "a") as out:
            line = [int(self.get_step), self.update_buffer.num_experiences, self.brain_name]
            out.write(json.dumps(line) + "\n")
        return update(self)

    trainer._update_policy = logged


def main() -> None:
    run_patched(wrap, sys.argv[1], sys.argv[1:])


if __name__ == "__main__":
    main()
