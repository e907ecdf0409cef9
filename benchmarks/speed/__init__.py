"""How fast: collection (raw Unity loop, our collector, torchrl's), the stand-in's own
cost, scaling with workers, the central parts' ceilings, the learner's updates and
threads, and Ray's start."""
