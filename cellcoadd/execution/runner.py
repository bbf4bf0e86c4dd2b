"""Running independent tasks with retries, here or on a dask cluster, and handing each
outcome on as it arrives.

One loop for both places, so that the rules are the same: a task that fails is tried
again (``retries`` times) unless its error is deterministic (:func:`is_deterministic`:
the same inputs would fail the same way), every failed attempt's reason is kept, and on
a cluster the number of times the scheduler moved a task after losing the worker that
ran it is kept too (a user's cluster reschedules such tasks itself, up to its
``allowed-failures``, so the caller's own retries never see them).

On dask, the last tasks are held back and submitted only when a worker is about to be
idle, each then cut into parts for the workers there are at that moment
(:func:`parts_per_task`): with ``cluster.adapt()`` the workers arrive during the run, so
the cut can only be chosen late.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

from cellcoadd.errors import ConfigError, InputError
from cellcoadd.execution.executors import import_distributed

T = TypeVar("T")


@dataclass
class Outcome(Generic[T]):
    """What became of one task: its result or its last error, after ``attempts`` tries.

    Attributes
    ----------
    item
        The task's item, as given.
    result
        What the task returned (None when it failed).
    error : BaseException or None
        The last attempt's error (None when it succeeded).
    attempts : int
        Tries made (1 when the first succeeded).
    retried : list of str
        Why each failed attempt before the last failed (``Type: message``).
    lost_workers : int
        Times the scheduler moved the task after the worker running it died (dask only).
    """

    item: T
    result: Any = None
    error: BaseException | None = None
    attempts: int = 1
    retried: list[str] = field(default_factory=list)
    lost_workers: int = 0

    @property
    def ok(self) -> bool:
        return self.error is None


def error_text(err: BaseException) -> str:
    """One short paragraph: the error's type and message (without a carried traceback)."""
    text = str(err).split("\nTraceback", 1)[0].strip()
    return f"{type(err).__name__}: {text}"[:2000]


def is_deterministic(err: BaseException) -> bool:
    """Whether trying again cannot help: a changed or refused input, a bad configuration
    (a damaged file or a lost worker may be transient: those are retried)."""
    return isinstance(err, InputError | ConfigError)


def parts_per_task(tasks: int, workers: int, most: int = 8) -> list[int]:
    """Into how many parts to cut each of ``tasks`` equal tasks, in the order they run,
    so that ``workers`` stay busy to the end.

    Whole tasks are the cheapest (a part repeats some of its task's set-up, and its
    results travel), so only the last ``tasks % workers`` are cut, each into ``workers``
    parts (at most ``most``): the whole ones keep every worker busy, and the parts share
    the remainder out. Nine tasks on two workers: eight whole, the ninth in two parts;
    100 on two: all whole; one on eight: eight parts.
    """
    if tasks <= 0:
        return []
    if workers <= 1:
        return [1] * tasks
    cut = tasks % workers
    return [1] * (tasks - cut) + [min(workers, most)] * cut


Done = Callable[[Outcome[T]], None]


def run_here(
    items: Sequence[T],
    work: Callable[[T], Any],
    done: Done[T],
    *,
    retries: int,
    progress: Any | None = None,
) -> None:
    """Run ``work(item)`` for each item in this process, one after the other, with
    retries; ``done`` gets each :class:`Outcome`; ``progress`` (a tqdm bar) is updated."""
    for item in items:
        outcome = Outcome(item, attempts=0)
        while outcome.attempts <= retries:
            outcome.attempts += 1
            try:
                outcome.result, outcome.error = work(item), None
                break
            except Exception as err:  # recorded: the run goes on with the others
                outcome.error = err
                if is_deterministic(err):
                    break
                if outcome.attempts <= retries:
                    outcome.retried.append(error_text(err))
        done(outcome)
        if progress is not None:
            progress.update(1)


#: ``submit(item, attempt, parts, key)``: the item's futures, the final one last
Submit = Callable[[T, int, int, str], list[Any]]


def _suspicious(dask_scheduler: Any, keys: list[str]) -> int:
    """On the scheduler: how often the tasks ``keys`` were on a worker that died."""
    total = 0
    for key in keys:
        state = dask_scheduler.tasks.get(key)
        total += int(getattr(state, "suspicious", 0) or 0) if state is not None else 0
    return total


def run_on_dask(
    client: Any,
    items: Sequence[T],
    submit: Submit[T],
    done: Done[T],
    *,
    retries: int,
    name: str = "cellcoadd-task",
    progress: Any | None = None,
    cut: bool = True,
) -> list[str]:
    """Run ``items`` (in this order, the costliest first) as dask tasks with retries;
    ``done`` gets each :class:`Outcome` as it arrives.

    The first tasks are submitted whole at once; the last ``2 x workers`` are held back
    until fewer tasks are left running than there are workers, then submitted each
    cut into the parts :func:`parts_per_task` gives all the tasks for the workers of
    that moment (``submit``'s ``parts``: 36 tasks on 2 workers, none cut; 9 on 2, the
    last in two). A retry is submitted whole. ``cut=False``: every task
    whole, all submitted at once.

    Returns the addresses of the workers that left the cluster during the run (killed,
    cancelled or retired: a scheduler that moves a task of a departing worker elsewhere
    by itself says nothing else about it).
    """
    distributed = import_distributed()
    workers = sum(client.nthreads().values())
    if workers == 0:
        client.wait_for_workers(1)  # an adaptive cluster that has not started one yet
        workers = sum(client.nthreads().values())
    seen: dict[str, None] = dict.fromkeys(client.nthreads())
    held = list(items)
    first = held[: max(len(held) - 2 * max(workers, 1), 0)] if cut else held
    held = held[len(first) :]
    running: dict[str, tuple[Outcome[T], list[Any]]] = {}

    def send(outcome: Outcome[T], parts: int) -> Any:
        key = f"{name}-{outcome.attempts}-{os.urandom(6).hex()}"
        futures = submit(outcome.item, outcome.attempts, parts, key)
        running[futures[-1].key] = (outcome, futures)
        return futures[-1]

    queue = distributed.as_completed([send(Outcome(item), 1) for item in first])

    def release_held() -> None:
        threads = client.nthreads()
        seen.update(dict.fromkeys(threads))
        now = max(sum(threads.values()), 1)
        if not held or len(running) >= now:
            return
        # the cut of all the tasks for the workers of this moment: only the last
        # ``len(items) % now`` are cut, as if every task had been planned for them
        plan = parts_per_task(len(items), now)[-len(held) :]
        for item, parts in zip(list(held), plan, strict=True):
            queue.add(send(Outcome(item), parts))
        held.clear()

    release_held()
    for future in queue:
        outcome, futures = running.pop(future.key)
        try:
            outcome.lost_workers += client.run_on_scheduler(
                _suspicious, keys=[f.key for f in futures]
            )
        except Exception:  # the scheduler's internals moved: the count is only a report
            pass
        try:
            outcome.result, outcome.error = future.result(), None
        except Exception as err:  # a failed task, a killed worker (KilledWorker)
            outcome.error = err
        finally:
            for item in futures:
                item.release()
        if outcome.error is not None and not is_deterministic(outcome.error):
            if outcome.attempts <= retries:
                outcome.retried.append(error_text(outcome.error))
                outcome.attempts += 1
                outcome.error = None
                queue.add(send(outcome, 1))
                release_held()
                continue
        done(outcome)
        if progress is not None:
            progress.update(1)
        release_held()
    current = client.nthreads()
    return [worker for worker in seen if worker not in current]
