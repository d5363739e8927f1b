"""Latency sweeps: a YAML spec expanded to episodes, run by parallel workers, kept in a durable store.

``spec``           the YAML spec, validated and expanded to one RunConfig per episode
``store``          the sweep folder: one atomically written record per finished episode
``worker``         one worker: episodes one after another, env and policy reused per task
``local``          the default pool: spawned worker processes that die with the sweep
``ray_pool``       the Ray pool: actors on a private loopback Ray or a cluster
``orchestrator``   ``run_sweep``: scheduling, records, retry of a crashed attempt
``identity``       the code a record was made by; a resume by other code refuses

The progress bar is the CLI's (``lq sweep``, lq_ros/cli/sweep.py). Layout of a sweep folder (``OUT``)::

    sweep.yaml             the spec as given (provenance)
    manifest.json          every episode key the spec expands to, with its configuration
    results/<key>.json     one finished episode (final status, scored row, attempts, ``code``: the identity of the
                           code that made it, lq_ros.run.sweep.identity); written atomically
    bags/<episode>/        the episode's rosbag2 bag (+ node logs for the ros transport)
    attempts/              a crashed first attempt (its bag, logs and record) before its retry
    logs/<key>.a<N>.log    worker-side output of attempt N
    episodes.jsonl         index of results/ (rebuilt at the end of a sweep; results/ is the truth)

An episode counts as finished only when ``results/<key>.json`` parses, names its key and its bag
exists; anything else (a half-written file, a bag without a record) is run again. The key is
``RunConfig.key()``, a hash of everything that determines the episode.
"""

from lq_ros.run.episode import TRANSPORTS
from lq_ros.run.sweep.local import LocalPool
from lq_ros.run.sweep.orchestrator import BACKENDS, MAX_ATTEMPTS, Job, Scheduler, SweepSummary, prepare, run_sweep
from lq_ros.run.sweep.ray_pool import RayConnectError, RayPool, ray_connect, ray_init_local
from lq_ros.run.sweep.spec import SpecError, SweepSpec, check_policies, expand_spec, load_spec
from lq_ros.run.sweep.store import ResultStore, StoreError, StoreLocked, atomic_write_text
from lq_ros.run.sweep.worker import EpisodeWorker, default_workers, env_key

__all__ = [
    "BACKENDS",
    "MAX_ATTEMPTS",
    "TRANSPORTS",
    "EpisodeWorker",
    "Job",
    "LocalPool",
    "RayConnectError",
    "RayPool",
    "ResultStore",
    "Scheduler",
    "SpecError",
    "StoreError",
    "StoreLocked",
    "SweepSpec",
    "SweepSummary",
    "atomic_write_text",
    "check_policies",
    "default_workers",
    "env_key",
    "expand_spec",
    "load_spec",
    "prepare",
    "ray_connect",
    "ray_init_local",
    "run_sweep",
]
