"""Rendering on a Dask cluster (mlaqc.optics.distributed): the image equals the local render bit for bit,
whatever the worker count, and a worker killed mid-render costs nothing but time."""

import dataclasses
import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest

from mlaqc.cli import main
from mlaqc.optics.config import load_config
from mlaqc.optics.distributed import render_on_cluster
from mlaqc.optics.errormap import ErrorMap
from mlaqc.optics.render import Renderer
from mlaqc.optics.scene import PointScene, TextureScene, WhiteScene

distributed = pytest.importorskip("distributed")

SMALL_TOML = Path(__file__).resolve().parent.parent / "fixtures" / "small_camera.toml"
SMALL = load_config(SMALL_TOML)


@pytest.fixture(scope="module")
def dask_cluster():
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as lc:
        yield lc


@pytest.fixture(scope="module")
def client(dask_cluster):
    with distributed.Client(dask_cluster, set_as_default=False) as c:
        yield c


def _errors():
    em = ErrorMap.zeros(24, 24).with_lens(5, 6, pitch_um=3, pitch_dir_deg=30).with_lens(10, 14, radius_front_rel=0.1)
    return em.with_globals(mla_rotation_deg=0.4, mla_shift_y_um=7)


def _small_batches(cfg):
    """Batches of 4,096 rays: a small render still makes dozens of chunks (tasks)."""
    return dataclasses.replace(cfg, trace=dataclasses.replace(cfg.trace, batch_rays=1 << 12))


@pytest.mark.parametrize("sampler", ["sobol", "random"])
@pytest.mark.parametrize("scene", [WhiteScene(), TextureScene(np.add.outer(np.arange(7), np.arange(11)) % 3 / 2.0),
                                   PointScene(((0.1, 0.2), (-0.4, 0.3)), 1e5)])
def test_cluster_render_equals_the_local_render_bit_for_bit(client, scene, sampler):
    cfg = _small_batches(SMALL)
    r = Renderer(cfg, _errors(), sampler=sampler)
    local = r.render(scene, rays=3_000_000, seed=5, threads=2)
    remote = render_on_cluster(client, r, scene, rays=3_000_000, seed=5)
    assert len(r.plan(scene, 3_000_000, None, 5).chunks()) > 5
    assert np.array_equal(local.photons, remote.photons)
    assert (local.rays_traced, local.rays_landed) == (remote.rays_traced, remote.rays_landed)


def test_one_worker_and_two_workers_give_the_same_image(client, dask_cluster):
    r = Renderer(_small_batches(SMALL))
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=":0") as one:
        with distributed.Client(one, set_as_default=False) as c1:
            a = render_on_cluster(c1, r, WhiteScene(), rays_per_pixel=8, seed=2).photons
    b = render_on_cluster(client, r, WhiteScene(), rays_per_pixel=8, seed=2).photons
    assert np.array_equal(a, b)


def test_a_worker_killed_mid_render_costs_nothing(tmp_path):
    """Kill one of two worker processes after a few chunks came back: its chunks run again on the other
    (and on its restarted self), and the image is still the local one."""
    r = Renderer(_small_batches(SMALL), _errors())
    local = r.render(WhiteScene(), rays_per_pixel=60, seed=9)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as lc:
        with distributed.Client(lc, set_as_default=False) as c:
            pids = c.run(os.getpid)
            victim = sorted(pids.values())[0]
            seen = []

            def progress(done, total):
                seen.append(done)
                if len(seen) == 5:
                    os.kill(victim, signal.SIGKILL)

            remote = render_on_cluster(c, r, WhiteScene(), rays_per_pixel=60, seed=9, progress=progress)
            assert victim not in c.run(os.getpid).values()  # it did die (the nanny started a new one)
    assert len(seen) > 20 and seen[-1] == local.rays_traced
    assert np.array_equal(local.photons, remote.photons)


def test_simulate_on_the_cluster_writes_the_same_raw(dask_cluster, tmp_path, capsys):
    here, there = tmp_path / "here.npy", tmp_path / "there.npy"
    args = ["simulate", "-c", str(SMALL_TOML), "--random-defects", "2", "--seed", "3", "--rays-per-pixel", "4"]
    assert main([*args, "--out", str(here), "-q"]) == 0
    assert main([*args, "--out", str(there), "--scheduler", dask_cluster.scheduler_address]) == 0
    assert "Dask: 2 workers" in capsys.readouterr().err
    assert np.array_equal(np.load(here), np.load(there))
    a, b = (json.loads((tmp_path / f"{n}.npy.sim.json").read_text()) for n in ("here", "there"))
    assert a["rays_traced"] == b["rays_traced"] and a["sampler"] == b["sampler"] == "sobol"


def test_signature_tables_built_on_the_cluster_equal_the_local_build(client):
    from mlaqc.models.signatures import build_signature_set

    local = build_signature_set(SMALL, rays_per_pixel=10)
    remote = build_signature_set(SMALL, rays_per_pixel=10, client=client)
    assert json.dumps(local.to_json_dict()) == json.dumps(remote.to_json_dict())


def test_models_command_builds_into_the_cache_on_the_cluster(dask_cluster, tmp_path, monkeypatch, capsys):
    from mlaqc.models import assembly_model, signatures
    from mlaqc.models.reference import config_key
    from mlaqc.models.signatures import signature_key

    # The command's own path (reference, then signature renders on the cluster, then the cache) at 10 rays
    # per pixel, not the tables' 400: the table a cluster builds is the local one (the test above).
    build = signatures.build_signature_set
    monkeypatch.setattr(signatures, "build_signature_set", lambda cfg, **kw: build(cfg, **kw, rays_per_pixel=10))
    build_assembly = assembly_model.build_assembly_model
    monkeypatch.setattr(assembly_model, "build_assembly_model",
                        lambda cfg, **kw: build_assembly(cfg, **kw, rays_per_pixel=10))
    monkeypatch.setenv("MLAQC_CACHE", str(tmp_path))
    monkeypatch.setenv("MLAQC_SCHEDULER", dask_cluster.scheduler_address)
    assert main(["models", "-c", str(SMALL_TOML), "--rebuild"]) == 0
    err = capsys.readouterr().err
    assert "Dask: 2 workers" in err and str(tmp_path) in err
    assert (tmp_path / f"reference_{config_key(SMALL)}.npz").is_file()
    assert (tmp_path / f"signatures_{signature_key(SMALL)}.json").is_file()
    assert len(list(tmp_path.glob("throughfocus_*.npz"))) == 1  # the shipped protocol's model
    assert (tmp_path / f"assembly_{assembly_model.assembly_key(SMALL)}.json").is_file()
