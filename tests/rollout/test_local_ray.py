"""Local Ray's object store fits the /dev/shm it is given (a container's --shm-size)."""

from __future__ import annotations

import os

from rollout.local_ray import RAY_MIN_OBJECT_STORE, _shm_free, object_store_bytes

GIB = 1024**3


def test_a_small_shm_gets_a_store_that_fits_it():
    # docker run --shm-size=2g on a 24 GiB host: Ray's default (7.2 GiB) would go to /tmp
    size = object_store_bytes(shm_free=2 * GIB, memory=24 * GIB)
    assert size is not None and RAY_MIN_OBJECT_STORE <= size <= 2 * GIB


def test_a_large_shm_keeps_rays_default():
    assert object_store_bytes(shm_free=12 * GIB, memory=24 * GIB) is None


def test_below_rays_minimum_ray_decides():
    # Docker's default 64 MB: nothing fits; Ray falls back to /tmp and says how to fix it
    assert object_store_bytes(shm_free=64 * 1024**2, memory=24 * GIB) is None


def test_reads_this_machines_shm():
    assert _shm_free() > 0


def test_local_mode_gives_rays_gcs_time_on_a_busy_machine(monkeypatch):
    import ray

    from rollout import local_ray

    started = {}
    monkeypatch.delenv(local_ray.GCS_WAIT, raising=False)
    monkeypatch.setattr(ray, "init", lambda **kwargs: started.update(kwargs))
    local_ray.init_local_ray(2)
    assert started["num_cpus"] == 2
    assert int(os.environ[local_ray.GCS_WAIT]) >= 120  # Ray's own: 30 s
    monkeypatch.setenv(local_ray.GCS_WAIT, "45")  # the user's choice stands
    local_ray.init_local_ray(2)
    assert os.environ[local_ray.GCS_WAIT] == "45"
