"""lq_ros/sim/model_cache.py: a compiled model read back from its MJB file is the compiled one, field for field
and step for step; the cache's settings, trimming and failures."""

from __future__ import annotations

import os
import time
from pathlib import Path

import mujoco
import numpy as np
import pytest

from lq_ros.sim import libero_env, model_cache

SCENE = """
<mujoco>
  <worldbody>
    <geom type="plane" size="1 1 0.1"/>
    <body pos="0 0 0.3"><freejoint/><geom type="box" size="0.05 0.04 0.03" mass="0.2"/></body>
    <body pos="0.02 0 0.5"><freejoint/><geom type="sphere" size="0.04" mass="0.1"/></body>
  </worldbody>
</mujoco>
"""


def model_arrays(model) -> dict[str, np.ndarray]:
    return {n: getattr(model, n) for n in dir(model) if isinstance(getattr(model, n, None), np.ndarray)}


def assert_same_model(a, b) -> None:
    arrays_a, arrays_b = model_arrays(a), model_arrays(b)
    assert arrays_a.keys() == arrays_b.keys()
    differ = [n for n in arrays_a if not np.array_equal(arrays_a[n], arrays_b[n])]
    assert not differ, differ


@pytest.fixture
def cache(tmp_path, monkeypatch) -> Path:
    folder = tmp_path / "models"
    monkeypatch.setenv("LQ_MODEL_CACHE", str(folder))
    monkeypatch.delenv("LQ_MODEL_CACHE_MB", raising=False)
    return folder


class CountingCompiler:
    def __init__(self) -> None:
        self.calls = 0

    def __call__(self, xml: str):
        self.calls += 1
        return mujoco.MjModel.from_xml_string(xml)


def test_a_model_is_compiled_once_then_read_back_identical(cache):
    compiler = CountingCompiler()
    compiled = model_cache.load_or_compile(SCENE, compiler)
    model_cache.wait_for_saves()
    files = list(cache.glob("*.mjb"))
    assert compiler.calls == 1 and len(files) == 1
    loaded = model_cache.load_or_compile(SCENE, compiler)
    assert compiler.calls == 1, "the second process's model came from the file"
    assert_same_model(compiled, loaded)
    # and it steps the same, bit for bit
    data = [mujoco.MjData(m) for m in (compiled, loaded)]
    for _ in range(200):
        for m, d in zip((compiled, loaded), data, strict=True):
            mujoco.mj_step(m, d)
    assert np.array_equal(data[0].qpos, data[1].qpos) and np.array_equal(data[0].qvel, data[1].qvel)


def test_the_file_is_written_in_the_background_and_a_second_lookup_waits_for_it(cache, monkeypatch):
    """The compiled model is returned before its file is written; a lookup of the same scene meanwhile reads the
    file once written instead of compiling again."""
    import threading

    writing, finished = threading.Event(), threading.Event()
    save = model_cache.save

    def slow_save(*args) -> None:
        writing.set()
        assert finished.wait(30)
        save(*args)

    monkeypatch.setattr(model_cache, "save", slow_save)
    compiler = CountingCompiler()
    model_cache.load_or_compile(SCENE, compiler)  # returns while the save waits
    assert writing.wait(30) and not list(cache.glob("*.mjb"))
    threading.Timer(0.2, finished.set).start()
    assert model_cache.load_or_compile(SCENE, compiler).nbody == 3
    assert compiler.calls == 1 and len(list(cache.glob("*.mjb"))) == 1


def test_another_xml_or_mujoco_version_is_another_file():
    key = model_cache.model_key(SCENE, "2.3.7")
    assert key != model_cache.model_key(SCENE + " ", "2.3.7")
    assert key != model_cache.model_key(SCENE, "3.1.0")


@pytest.mark.parametrize("damage", ["not a model", "truncated"])
def test_an_unreadable_file_is_compiled_again_and_replaced(cache, tmp_path, monkeypatch, damage):
    monkeypatch.chdir(tmp_path)  # (where MuJoCo would log a bad file)
    compiler = CountingCompiler()
    model_cache.load_or_compile(SCENE, compiler)
    model_cache.wait_for_saves()
    (path,) = cache.glob("*.mjb")
    path.write_bytes(b"not a model" if damage == "not a model" else path.read_bytes()[:1000])
    model = model_cache.load_or_compile(SCENE, compiler)
    assert compiler.calls == 2 and model.nbody == 3
    model_cache.wait_for_saves()
    assert mujoco.MjModel.from_binary_path(str(path)).nbody == 3
    assert not (tmp_path / "MUJOCO_LOG.TXT").exists() or damage == "truncated"


def test_a_folder_that_cannot_be_written_only_means_no_cache(tmp_path, monkeypatch):
    blocked = tmp_path / "file"
    blocked.write_text("a file where the folder should be")
    monkeypatch.setenv("LQ_MODEL_CACHE", str(blocked / "models"))
    compiler = CountingCompiler()
    assert model_cache.load_or_compile(SCENE, compiler).nbody == 3
    assert model_cache.load_or_compile(SCENE, compiler).nbody == 3
    model_cache.wait_for_saves()
    assert compiler.calls == 2
    assert [p.name for p in tmp_path.iterdir()] == ["file"], "no temporary file left"


def test_off_and_zero_disable_it(cache, monkeypatch):
    for variable, value in (("LQ_MODEL_CACHE", "off"), ("LQ_MODEL_CACHE_MB", "0")):
        with monkeypatch.context() as patch:
            patch.setenv(variable, value)
            assert model_cache.settings()[0] is None
            model_cache.load_or_compile(SCENE, CountingCompiler())
    assert not cache.exists()


def test_settings_default_folder_and_limit(tmp_path):
    folder, limit = model_cache.settings({"XDG_CACHE_HOME": str(tmp_path)})
    assert folder == tmp_path / "lq_ros" / "mujoco_models"
    assert limit == model_cache.DEFAULT_LIMIT_MB * 1024 * 1024
    assert model_cache.settings({"LQ_MODEL_CACHE": "/x", "LQ_MODEL_CACHE_MB": "5"}) == (Path("/x"), 5 * 1024 * 1024)


def test_a_bad_limit_is_one_line_naming_the_variable():
    with pytest.raises(ValueError, match=r"^LQ_MODEL_CACHE_MB='lots': expected a whole number of megabytes"):
        model_cache.settings({"LQ_MODEL_CACHE_MB": "lots"})


def test_trim_removes_the_least_recently_used_and_stale_temporaries(tmp_path):
    now = time.time()
    for age_s, name in ((300, "old"), (200, "middle"), (100, "new")):
        path = tmp_path / f"{name}.mjb"
        path.write_bytes(b"x" * 1000)
        os.utime(path, (now - age_s, now - age_s))
    stale, fresh = tmp_path / ".a.1.tmp", tmp_path / ".b.2.tmp"
    for path, age_s in ((stale, model_cache.STALE_TEMPORARY_S + 10), (fresh, 1)):
        path.write_bytes(b"partial")
        os.utime(path, (now - age_s, now - age_s))
    model_cache.trim(tmp_path, 2000, keep=tmp_path / "old.mjb")
    assert sorted(p.name for p in tmp_path.iterdir()) == [".b.2.tmp", "new.mjb", "old.mjb"]


@pytest.mark.slow
@pytest.mark.sim
def test_a_libero_scene_read_from_the_cache_runs_the_compiled_episode(cache, monkeypatch):
    """Two envs of one task, the first compiling its scene (and writing the MJB), the second reading it: the same
    model and 30 ticks of the same full state."""

    def episode() -> tuple[object, list[np.ndarray]]:
        libero_env._compiled_models.clear()  # (else the second env copies the first's model in memory)
        env = libero_env.LiberoEnv("libero_object", 2)
        try:
            env.reset(0, 7)
            rng = np.random.default_rng(5)
            states = []
            for _ in range(30):
                env.step(np.concatenate([rng.uniform(-0.5, 0.5, 6), [rng.choice([-1.0, 1.0])]]))
                d = env._env.env.sim.data._data
                states.append(np.concatenate([d.qpos, d.qvel, d.qacc, d.qacc_warmstart, d.act, d.ctrl]))
            return env._env.env.sim.model._model, states
        finally:
            env.close()

    compiles = CountingCompiler()
    original = model_cache.load_or_compile
    monkeypatch.setattr(model_cache, "load_or_compile", lambda xml, compile_xml: original(xml, compiles))
    compiled_model, compiled = episode()
    model_cache.wait_for_saves()
    assert compiles.calls == 1 and len(list(cache.glob("*.mjb"))) == 1
    loaded_model, loaded = episode()
    assert compiles.calls == 1, "the second env read its scene from the cache"
    assert_same_model(compiled_model, loaded_model)
    for tick, (a, b) in enumerate(zip(compiled, loaded, strict=True)):
        assert np.array_equal(a, b), f"tick {tick}"
