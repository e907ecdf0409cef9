"""The one C extension; everything else about the package is in pyproject.toml.

unitysim's 3DBall physics in C (``unitysim/envs/_ball3d.c``). It is optional: where no C
compiler is found the install goes on and the player runs the numpy twin of the same
equations. ``-ffp-contract=off`` keeps every product rounded on its own, as numpy rounds
it, so both give the same trajectories (to the last bit wherever numpy's sin and cos are
libm's).
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "unitysim.envs._ball3d",
            ["unitysim/envs/_ball3d.c"],
            extra_compile_args=["-O2", "-ffp-contract=off"],
            optional=True,
        )
    ]
)
