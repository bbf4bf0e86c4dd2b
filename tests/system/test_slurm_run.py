"""A survey run on SLURM through dask-jobqueue, as docs/survey-runs.md shows it: two bands,
two tracts, workers as SLURM jobs; one job is cancelled (``scancel``) while its worker builds
a patch, and the run still builds every patch, byte for byte as the serial run does.

Needs a running SLURM whose jobs can reach this machine's loopback address:
``make test-slurm`` starts a single-host one (tests/system/slurm/start_slurm.sh) and runs
these tests (``pytest -m slurm tests/system``); the default suite leaves them out."""

from __future__ import annotations

import filecmp
import shutil
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import dask
import pytest
from run_factory import BUILD, survey_skymap, write_survey

from cellcoadd.io.exposures.index import ExposureIndex, absolute_entry
from cellcoadd.model.manifest import ManifestEntry

pytestmark = pytest.mark.slurm

#: 2 bands x 2 tracts x 2 x 2 patches
N_PATCHES = 16
#: the run on SLURM takes ~10 s here: a hung run fails the test after this
RUN_TIMEOUT_S = 180


def _slurm_ready() -> str | None:
    """Why SLURM cannot run the tests here (None when it can)."""
    if shutil.which("sinfo") is None or shutil.which("sbatch") is None:
        return "no SLURM commands (sinfo, sbatch): run `make test-slurm`"
    try:
        states = subprocess.run(
            ["sinfo", "-h", "-o", "%T"], capture_output=True, text=True, timeout=20
        )
    except subprocess.TimeoutExpired:
        return "sinfo did not answer in 20 s: is slurmctld running? (`make test-slurm`)"
    if states.returncode != 0:
        return f"sinfo failed: {states.stderr.strip()} (`make test-slurm` starts SLURM)"
    if not {"idle", "mixed"} & set(states.stdout.split()):
        return f"no SLURM node takes jobs (states: {states.stdout.split()})"
    return None


@pytest.fixture(scope="module")
def slurm() -> None:
    reason = _slurm_ready()
    if reason is not None:
        pytest.skip(reason)


def _worker_environment() -> dict[str, str]:
    try:
        from cellcoadd.execution import dask_worker_environment
    except ImportError:  # where the executors still live in the builder
        from cellcoadd.builder.executors import dask_worker_environment
    return dask_worker_environment()


def _cluster(tmp_path: Path, job_name: str):
    """A SLURMCluster built as docs/survey-runs.md builds it: one single-threaded worker per
    job, the worker settings in the job script's environment. Everything listens on the
    loopback address; the jobs run and log under ``tmp_path``."""
    from dask_jobqueue import SLURMCluster

    prologue = [f"export {name}={value}" for name, value in _worker_environment().items()]
    return SLURMCluster(
        cores=1,
        processes=1,
        memory="2GB",
        walltime="00:20:00",
        job_script_prologue=prologue,
        python=sys.executable,
        job_name=job_name,
        log_directory=str(tmp_path / "slurm-logs"),
        job_extra_directives=[f"--chdir={tmp_path}"],
        scheduler_options={"host": "127.0.0.1", "dashboard_address": None},
        worker_extra_args=["--host", "127.0.0.1", "--no-dashboard"],
    )


def _squeue(job_name: str) -> dict[str, str]:
    """Job id -> state of this test's jobs still known to SLURM."""
    out = subprocess.run(
        ["squeue", "-h", "-n", job_name, "-o", "%i %T"],
        capture_output=True, text=True, timeout=20, check=True,
    ).stdout  # fmt: skip
    return dict(line.split() for line in out.splitlines() if line.strip())


def _cancel_leftovers(job_name: str) -> None:
    """scancel this test's jobs that outlived the cluster (by id)."""
    try:
        ids = list(_squeue(job_name))
    except (subprocess.SubprocessError, OSError):
        return
    if ids:
        subprocess.run(["scancel", *ids], timeout=20, check=False)


def _wait(condition, timeout: float, what: str, interval: float = 0.1):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(interval)
    raise TimeoutError(f"{what}: not after {timeout:.0f} s")


def _bounded(call, timeout: float, what: str):
    """``call()`` in a thread, given up (TimeoutError) after ``timeout`` seconds: the test
    then closes the cluster and cancels its jobs, which ends the call."""
    outcome: dict[str, object] = {}

    def target() -> None:
        try:
            outcome["value"] = call()
        except BaseException as error:
            outcome["error"] = error

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(timeout)
    if thread.is_alive():
        raise TimeoutError(f"{what}: not done after {timeout:.0f} s")
    if "error" in outcome:
        raise outcome["error"]  # type: ignore[misc]
    return outcome["value"]


class JobCanceller(threading.Thread):
    """Cancels (``scancel``) the SLURM job of a worker that is building a patch, then asks
    the cluster for its jobs again, so that a replacement job starts. Every wait is bounded;
    what went wrong is kept in ``error``."""

    def __init__(self, cluster, client, out: Path, timeout: float = 120.0):
        super().__init__(daemon=True)
        self.cluster, self.client, self.out, self.timeout = cluster, client, out, timeout
        self.cancelled: str | None = None  # job id
        self.built_before: int | None = None  # patch files written when it was cancelled
        self.replacement: str | None = None  # job id
        self.error: BaseException | None = None

    def _busy_job(self) -> tuple[str, str] | None:
        """(worker name, job id) of a worker with a task in progress."""
        names = {
            address: info["name"]
            for address, info in self.client.scheduler_info()["workers"].items()
        }
        for address, keys in self.client.processing().items():
            job = self.cluster.workers.get(names.get(address))
            if keys and job is not None and job.job_id:
                return names[address], job.job_id
        return None

    def run(self) -> None:
        try:
            name, job_id = _wait(self._busy_job, self.timeout, "a worker building a patch")
            time.sleep(0.5)  # mid-patch
            subprocess.run(["scancel", job_id], check=True, timeout=20)
            self.cancelled = job_id
            self.built_before = len(list(self.out.rglob("patch_*")))
            # the scheduler drops the worker; the cluster forgets its job ...
            _wait(
                lambda: getattr(self.cluster.workers.get(name), "job_id", None) != job_id,
                60, f"the cluster dropping cancelled job {job_id}",
            )  # fmt: skip
            # ... and, asked for its 2 jobs again, submits a new one under the same name
            self.cluster.scale(jobs=2)
            self.replacement = _wait(
                lambda: getattr(self.cluster.workers.get(name), "job_id", None),
                60, "a replacement job",
            )  # fmt: skip
        except BaseException as error:  # reported by the test
            self.error = error


#: the cluster forgets a lost worker's job after 1 s, not dask's 15 s (only then does
#: ``cluster.scale`` submit a job in its place)
QUICK_LOSS = {"distributed.deploy.lost-worker-timeout": "1s"}


def _index(root: Path) -> Path:
    paths = write_survey(root / "inputs", bands=("g", "r"), n_visits=2)
    db = root / "inputs.sqlite"
    with ExposureIndex(db) as index:
        update = index.update([absolute_entry(ManifestEntry(path=str(p)), ".") for p in paths])
        assert not update.bad, update.bad
    return db


def _outputs(out: Path) -> list[str]:
    """The run's output files, relative to ``out``, without the run's own records (the
    ledger and report, which hold times and hosts)."""
    records = {"ledger.sqlite", "report.json"}
    return sorted(
        str(p.relative_to(out))
        for p in out.rglob("*")
        if p.is_file() and p.name not in records and not p.name.startswith("ledger.sqlite")
    )


def test_slurm_cluster_replaces_a_cancelled_job(slurm, tmp_path):
    """The SLURM side alone: jobs start, their workers connect over loopback, a cancelled
    job's worker goes away and asking for the jobs again brings a new one."""
    from distributed import Client

    job_name = f"cc-{uuid.uuid4().hex[:8]}"
    try:
        with (
            dask.config.set(QUICK_LOSS),
            _cluster(tmp_path, job_name) as cluster,
            Client(cluster) as client,
        ):
            cluster.scale(jobs=2)
            client.wait_for_workers(2, timeout=90)
            assert client.gather(client.map(lambda x: x * x, range(8))) == [x * x for x in range(8)]
            assert len(_squeue(job_name)) == 2
            name, job = sorted(cluster.workers.items())[0]
            job_id = job.job_id
            del job  # the cluster asserts on close that every job object it made is closed
            subprocess.run(["scancel", job_id], check=True, timeout=20)
            _wait(lambda: len(client.scheduler_info()["workers"]) == 1, 60, "the worker leaving")
            _wait(lambda: name not in cluster.workers, 60, "the cluster dropping the job")
            cluster.scale(jobs=2)
            client.wait_for_workers(2, timeout=90)
            assert job_id not in _squeue(job_name)
            assert cluster.workers[name].job_id != job_id
            assert client.submit(sum, [1, 2, 3]).result(timeout=60) == 6
    finally:
        _cancel_leftovers(job_name)


def test_survey_run_on_slurm_survives_a_cancelled_job(slurm, tmp_path):
    from distributed import Client

    from cellcoadd.pipelines.survey import run_survey

    db = _index(tmp_path)
    skymap = survey_skymap()
    serial = run_survey(
        db, skymap, tmp_path / "serial", config=BUILD, workers=1, progress=False, figure=False
    )
    assert not serial.failed and len(serial.built) == N_PATCHES, serial.summary()

    job_name = f"cc-{uuid.uuid4().hex[:8]}"
    canceller = None
    try:
        with (
            dask.config.set(QUICK_LOSS),
            _cluster(tmp_path, job_name) as cluster,
            Client(cluster) as client,
        ):
            cluster.scale(jobs=2)
            # both workers up before the run: the cancelled job is then one of two
            client.wait_for_workers(2, timeout=90)
            canceller = JobCanceller(cluster, client, tmp_path / "slurm")
            canceller.start()
            result = _bounded(
                lambda: run_survey(
                    db, skymap, tmp_path / "slurm", scheduler=client, retries=3,
                    config=BUILD, progress=False, figure=False,
                ),
                RUN_TIMEOUT_S, "the run on SLURM",
            )  # fmt: skip
            canceller.join(timeout=90)
            assert not canceller.is_alive(), "the canceller did not finish"
    finally:
        _cancel_leftovers(job_name)
    assert canceller.error is None, repr(canceller.error)
    assert canceller.cancelled and canceller.replacement != canceller.cancelled
    assert canceller.built_before is not None and canceller.built_before < N_PATCHES
    assert not result.failed, result.summary()
    assert len(result.built) == N_PATCHES, result.summary()
    # (result.lost_workers may be 0: a worker that gets SLURM's SIGTERM in time says goodbye,
    # and the scheduler then moves its patches without counting the worker as lost)
    names = _outputs(tmp_path / "serial")
    assert len([n for n in names if n.endswith(".fits")]) == N_PATCHES, names
    assert _outputs(tmp_path / "slurm") == names
    differ = [
        n for n in names if not filecmp.cmp(tmp_path / "serial" / n, tmp_path / "slurm" / n, False)
    ]
    assert not differ, differ
