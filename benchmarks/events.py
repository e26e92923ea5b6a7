"""The runs benchmarks/report.py reads: TensorBoard event files, checked record by record, each
run's scalars (resumed attempts joined as TensorBoard joins them), every run folder of a suite
into groups, the run folders left out and why, and an export (``curves.json``) read back."""

import json
import re
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np

from benchmarks.run import running as live_pid
from benchmarks.stats import final_performance, steps_to_threshold

DIAGNOSTICS = (
    "ipg/effective_nu",
    "ipg/grad_var",
    "ipg/grad_var_cv",
    "ipg/corr_adv_cv",
    "qprop/grad_var",
    "qprop/grad_var_cv",
    "qprop/corr_adv_cv",
)
TAGS = (
    "charts/episodic_return",
    "charts/episodic_length",
    "charts/success_rate",
    "charts/policy_entropy",
    "charts/SPS",
    "eval/episodic_return",
    "eval/success_rate",
    *DIAGNOSTICS,
)
# the window of an export from before runs kept theirs: the default then, with which every
# committed export was made (their results.md say so)
UNRECORDED_WINDOW = 100


class CorruptEventFile(ValueError):
    """An event file with a record whose checksum fails: damaged, not to be read as data."""


def read_events(path: Path) -> list:
    """The events of one event file, a TFRecord file: per record its length (8 bytes), that
    length's masked CRC-32C, the event and the event's CRC. TensorBoard's loader stops silently at
    a damaged record; here a failed checksum raises CorruptEventFile, and a record cut short at
    the end (its writer killed mid-write) ends the file with a warning naming it."""
    from tensorboard.compat.proto.event_pb2 import Event
    from tensorboard.compat.tensorflow_stub.pywrap_tensorflow import masked_crc32c

    data, pos, events = path.read_bytes(), 0, []
    while pos < len(data):
        length, body = data[pos : pos + 8], pos + 12
        end = body + int.from_bytes(length, "little")
        for checked, crc in ((length, data[pos + 8 : body]), (data[body:end], data[end : end + 4])):
            if len(crc) < 4:
                print(
                    f"warning: {path}: its last record is cut short; read the {len(events)} events before it", file=sys.stderr
                )
                return events
            if masked_crc32c(checked) != int.from_bytes(crc, "little"):
                raise CorruptEventFile(f"{path}: the record at byte {pos} fails its checksum")
        events.append(Event.FromString(data[body:end]))
        pos = end + 4
    return events


def read_run(run_dir: Path, tags=TAGS) -> dict:
    """Every tag of ``tags`` of one run, as {tag: [[step, value], ...]}, plus its wall time. A
    resumed run has an event file per attempt, read here in the order they were written: one
    opens with a SessionLog START at its ``purge_step`` (common/run.py), and as in TensorBoard
    the points logged before it at that step or later (a killed attempt's) are dropped. The wall
    time sums the attempts' (the pauses not counted). A damaged event file raises
    CorruptEventFile."""
    from tensorboard.compat.proto.event_pb2 import SessionLog

    files = [read_events(f) for f in run_dir.glob("events.out.tfevents.*")]
    out, text, wall_time = {}, None, 0.0
    for events in sorted(filter(None, files), key=lambda events: events[0].wall_time):
        times = [e.wall_time for e in events for v in e.summary.value if v.tag in tags]
        wall_time += max(times) - min(times) if times else 0.0
        for e in events:
            if e.session_log.status == SessionLog.START:  # a resumed attempt, from e.step on
                out = {tag: [p for p in points if p[0] < e.step] for tag, points in out.items()}
            for v in e.summary.value:
                if v.tag in tags:
                    out.setdefault(v.tag, []).append([e.step, round(v.simple_value, 5)])
                elif v.tag == "hyperparameters/text_summary" and text is None:
                    text = v.tensor.string_val[0].decode()
    out["wall_time"] = wall_time
    if text is not None:
        cells = [line.strip("|").split("|") for line in text.splitlines()]
        keep = ("eval_episodes", "total_timesteps")
        out["args"] = {c[0]: c[1] for c in cells if len(c) == 2 and c[0] in keep}
    return out


def downsample(points: list, n: int = 300) -> list:
    """At most ``n`` points: the mean value of consecutive chunks, at each chunk's last step."""
    if len(points) <= n:
        return points
    return [[int(c[-1, 0]), round(float(c[:, 1].mean()), 5)] for c in np.array_split(np.array(points, float), n)]


def collect(runs_dir: Path, window: int, include_unfinished: bool = False) -> dict:
    """{group "name__env_id": {seed: run}} from the folders run.py wrote. Each run keeps its
    summary (``final``, ``reach``) computed from the full event data over the last ``window``
    training episodes (kept as ``window``), and curves downsampled for plotting: the export stays
    small and still reproduces the table exactly, over that window only. Only runs whose
    ``exit_code`` is 0 are read, or with ``include_unfinished``, also those that were stopped (no
    exit code, or a signal's) with a resume point to go on from, kept with ``unfinished_at``, the
    last step they logged. Every other run folder is left out with a warning saying why (failed,
    stopped, still running, no exit code), as is one whose event files are damaged or hold no
    scalars."""
    groups = defaultdict(dict)
    for folder in sorted(p for p in runs_dir.iterdir() if p.is_dir()):
        code = folder / "exit_code"
        text = code.read_text().strip() if code.exists() else None
        code = int(text) if text and re.fullmatch(r"-?[0-9]+", text) else None
        stopped = code is None or code < 0 or code in (130, 137, 143)  # killed, not failed
        resumable = stopped and any(folder.glob("*/resume.pt"))
        done = code == 0
        if not (done or (include_unfinished and resumable)):
            why = left_out(folder, text, code, stopped, resumable)
            print(f"warning: {folder}: {why}", file=sys.stderr)
            continue
        name, env_id, seed = folder.name.split("__")
        event_dirs = [p for p in folder.iterdir() if p.is_dir()]
        try:
            run = read_run(max(event_dirs)) if event_dirs else {}
        except CorruptEventFile as error:
            print(f"warning: {error}: the file is damaged; run {folder} left out", file=sys.stderr)
            continue
        steps = [points[-1][0] for tag, points in run.items() if tag in TAGS and points]
        if not steps:
            print(f"warning: {folder}: no scalars in its event files; left out", file=sys.stderr)
            continue
        if not done:
            run["unfinished_at"] = max(steps)
        run["final"] = final_performance(run, bool(run.get("charts/success_rate")), window)
        run["reach"] = steps_to_threshold(run, env_id, window)
        run["window"] = window
        for tag in (
            "charts/episodic_return",
            "charts/episodic_length",
            "charts/success_rate",
            "charts/policy_entropy",
            *DIAGNOSTICS,
        ):
            if tag in run:
                run[tag] = downsample(run[tag], 100 if tag in DIAGNOSTICS else 300)
        groups[f"{name}__{env_id}"][seed.removeprefix("seed")] = run
    return groups


def left_out(folder: Path, text: str | None, code: int | None, stopped: bool, resumable: bool) -> str:
    """Why a run folder is not read, for its warning. Only ``exit_code`` 0, which run.py writes
    when the run's process has ended, says that a run finished: without the file a run may be
    running, or may have been stopped with its runner (kill -9, a machine's end) at any step."""
    resume = "; --include-unfinished reads it at its last step" if resumable else ""
    if not stopped:
        return f"failed (exit code {code}, see its stderr.log); left out"
    if code is not None:
        return f"stopped by a signal (exit code {code}) before its end; left out{resume}"
    if text is not None:  # its runner was stopped while writing it
        return f"its exit_code holds {text!r}, not an exit code; left out{resume}"
    if pid := live_pid(folder):
        return f"still running (pid {pid}), so no exit_code yet; left out{resume}"
    return (
        "no exit_code, which benchmarks/run.py writes when a run ends, so it is not known to have "
        "finished (its runner was stopped first); left out: run.py on the suite again runs it to "
        f"its end, from its resume point if it has one{resume}"
    )


def read_export(path: Path) -> dict:
    """The runs of an export, {group "name__env_id": {seed: run}}, each with the ``window`` its
    summary was computed over (``UNRECORDED_WINDOW`` if it records none); ValueError for a file
    that is not one (damaged, or JSON of another shape: a list, a number)."""
    text = path.read_text()
    groups = json.loads(text)
    if not isinstance(groups, dict):
        raise ValueError(f'its JSON is {text.strip()[:20]!r}, not an object {{"name__env_id": ...}}')
    for group, runs in groups.items():
        if group.count("__") != 1 or not isinstance(runs, dict):
            raise ValueError(f'{group!r} is not a group "name__env_id" of runs {{seed: run}}')
        if not all(isinstance(run, dict) for run in runs.values()):
            raise ValueError(f"a run of {group} is not an object")
        for run in runs.values():
            run.setdefault("window", UNRECORDED_WINDOW)
    return groups
