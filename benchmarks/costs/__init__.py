"""What a run costs besides time: faults (a chaos run against a clean one), every
process's memory over a long run, and the learner's memory per buffered sample."""
