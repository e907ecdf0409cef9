"""The torch networks built from a ``BehaviorSpec``: sensor encoders, actor-critics, SAC's Q
networks, POCA's group critic, and their torchrl views."""
