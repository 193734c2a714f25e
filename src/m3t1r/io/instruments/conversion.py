"""From an instrument's file (and the robot's log) to the project's measurement table.

`convert_campaign` reads the tracker file in its format, turns a stream into static poses (still
stretches, averaged: `dwells`), takes the joint readings from the same file or pairs the poses with
the robot log's stops (by order, or by the clock offset it estimates) and returns the rows of a
measurement CSV: joint columns by name, `x, y, z` [m] (or `x1, y1, z1 ... xK, yK, zK` for every
marker with `--body all`, blank where a marker was not seen), `qx, qy, qz, qw` when the tracker measured
orientations, `source` (the tracker file's line, frame or message number of each pose's first
sample) and `position_std` [m] (each pose's scatter, when known).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from m3t1r.errors import DataFileError, InvalidInputError
from m3t1r.io.instruments.delimited import ReadOptions
from m3t1r.io.instruments.dwells import (
    ClockPairing,
    Stretch,
    average_positions,
    average_quaternions,
    pair_by_clock,
    pair_by_order,
    stationary_stretches,
)
from m3t1r.io.instruments.formats import read_robot_log, read_tracker
from m3t1r.io.instruments.records import TrackerRecord
from m3t1r.io.instruments.robot_log import RobotLog

__all__ = ["ConversionOptions", "Conversion", "convert_campaign"]


@dataclass(frozen=True)
class ConversionOptions:
    """format: a format name, or None to detect it from the content; read: what the file does not
    say (`ReadOptions`); still_speed [m/s] and robot_still_speed [rad/s or m/s]: below these a
    stream is still; min_dwell [s]: the shortest stop kept; pairing: "auto" (by clock when both
    sides have times, else by order), "order" or "time"."""

    format: str | None = None
    read: ReadOptions = field(default_factory=ReadOptions)
    still_speed: float = 5e-3
    robot_still_speed: float = 2e-3
    min_dwell: float = 0.5
    pairing: str = "auto"


@dataclass(frozen=True)
class Conversion:
    """The measurement table: columns, rows (n, len(columns)) in SI units, and what was done
    (`notes`, plain words), the pairing's clock offset [s] (robot minus tracker) when estimated."""

    columns: tuple[str, ...]
    rows: np.ndarray
    notes: tuple[str, ...]
    format: str
    clock_offset: float | None = None


@dataclass(frozen=True)
class _Poses:
    positions: np.ndarray
    quaternions: np.ndarray | None
    joints: np.ndarray
    sources: np.ndarray
    scatter: np.ndarray | None
    spans: list[Stretch] | None
    points: np.ndarray | None = None  # (n, K, 3) [m] every marker, NaN where not seen


def convert_campaign(tracker: Path, robot: Path | None, options: ConversionOptions) -> Conversion:
    """The measurement table of a campaign (module docstring). Raises DataFileError naming the file
    and line, InvalidInputError for what cannot be paired, MissingExtraError for a reader not
    installed."""
    notes: list[str] = []
    record = read_tracker(tracker, options.format, options.read, notes)
    notes.insert(0, f"{tracker}: {record.format}, {record.body}, {record.n_samples} samples")
    poses = _static_poses(record, options, notes)
    joint_names, joints, offset = record.joint_names, poses.joints, None
    if robot is not None:
        log = read_robot_log(robot, options.read.joints, options.read.joint_degrees)
        joint_names = log.joint_names
        joints, keep, offset = _pair(poses, log, options, notes)
        poses = _subset(poses, keep)
    elif not joint_names:
        raise InvalidInputError(f"{tracker} holds no joint readings: give the robot's log with --robot ROBOT_LOG")
    columns = list(joint_names)
    if poses.points is not None:
        columns += [f"{a}{k}" for k in record.point_numbers for a in "xyz"]
        blocks = [joints, poses.points.reshape(len(poses.points), -1)]
    else:
        columns += ["x", "y", "z"]
        blocks = [joints, poses.positions]
    if poses.quaternions is not None:
        columns += ["qx", "qy", "qz", "qw"]
        blocks.append(poses.quaternions)
    columns.append("source")
    blocks.append(poses.sources[:, None].astype(float))
    if poses.scatter is not None:
        columns.append("position_std")
        blocks.append(poses.scatter[:, None])
    rows = np.hstack(blocks)
    if len(rows) == 0:
        raise InvalidInputError(f"{tracker}: no pose left to write")
    return Conversion(tuple(columns), rows, tuple(notes), record.format, offset)


def _static_poses(record: TrackerRecord, options: ConversionOptions, notes: list[str]) -> _Poses:
    """One pose per still stretch of a stream, or per sample; unseen samples dropped (with a note)."""
    if record.times is None or record.format == "csv" and not _is_stream(record):
        seen = np.all(np.isfinite(record.positions), axis=1)
        if not seen.all():
            notes.append(
                f"{np.count_nonzero(~seen)} samples not seen (empty cells) left out: {record.source_kind}s "
                + ", ".join(str(s) for s in record.sources[~seen][:10])
            )
        quaternions = None if record.quaternions is None else record.quaternions[seen]
        scatter = None if record.scatter is None else record.scatter[seen]
        spans = None
        if record.times is not None:
            spans = [
                Stretch(int(k), int(k) + 1, float(t), float(t))
                for k, t in zip(np.flatnonzero(seen), record.times[seen])
            ]
        points = None if record.points is None else record.points[seen]
        return _Poses(
            record.positions[seen], quaternions, record.joints[seen], record.sources[seen], scatter, spans, points
        )
    tracked = record.positions if record.points is None else record.points
    stretches = stationary_stretches(record.times, tracked, options.still_speed, options.min_dwell)
    if not stretches:
        raise DataFileError(
            record.path,
            f"no still stretch of {options.min_dwell:g} s or more below "
            f"{options.still_speed:g} m/s (--still-speed, --min-dwell)",
        )
    averaged = [average_positions(record.positions[s.start : s.stop]) for s in stretches]
    quaternions = (
        None
        if record.quaternions is None
        else np.array([average_quaternions(record.quaternions[s.start : s.stop]) for s in stretches])
    )
    joints = np.array([record.joints[s.start : s.stop].mean(axis=0) for s in stretches])
    scatter = np.array([a[1] for a in averaged])
    points = None
    if record.points is not None:
        points = np.array([_point_means(record.points[s.start : s.stop]) for s in stretches])
        scatter = np.array([_point_scatter(record.points[s.start : s.stop], p) for s, p in zip(stretches, points)])
    notes.append(
        f"{len(stretches)} still stretches of {record.n_samples} frames averaged (median "
        f"{int(np.median([a[2] for a in averaged]))} frames, median scatter {np.median(scatter):.3g} m)"
    )
    return _Poses(
        np.array([a[0] for a in averaged]),
        quaternions,
        joints.reshape(len(stretches), -1),
        record.sources[[s.start for s in stretches]],
        scatter,
        stretches,
        points,
    )


def _point_scatter(points: np.ndarray, means: np.ndarray) -> float:
    """RMS distance [m] of every marker sample seen from its marker's mean (the centroid of the markers
    seen jumps when one hides, so the centroid's scatter would not be the tracker's)."""
    seen = np.isfinite(points).all(axis=2)
    return float(np.sqrt(np.mean(np.sum((points - means[None]) ** 2, axis=2)[seen])))


def _point_means(points: np.ndarray) -> np.ndarray:
    """(K, 3) the mean of each marker over the frames that saw it (NaN for one never seen) [m]."""
    seen = np.isfinite(points).all(axis=2)
    counts = seen.sum(axis=0)
    sums = np.where(seen[:, :, None], points, 0.0).sum(axis=0)
    return np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], np.nan)


def _is_stream(record: TrackerRecord) -> bool:
    """A CSV with a time column is a stream when consecutive samples come faster than 0.2 s apart."""
    return record.times is not None and len(record.times) > 1 and float(np.median(np.diff(record.times))) < 0.2


def _pair(
    poses: _Poses, log: RobotLog, options: ConversionOptions, notes: list[str]
) -> tuple[np.ndarray, np.ndarray, float | None]:
    """(joints (k, J) of the paired stops, indices of the poses kept, clock offset or None)."""
    stops, values = _robot_stops(log, options)
    timed = poses.spans is not None and stops is not None
    if options.pairing == "time" and not timed:
        raise InvalidInputError("--pair time needs times on both sides: the tracker file or the robot log has none")
    if options.pairing == "order" or not timed:
        pairing: ClockPairing = pair_by_order(len(poses.positions), len(values))
        notes.append(f"paired {pairing.paired} poses with the robot's stops by order")
    else:
        assert poses.spans is not None and stops is not None
        pairing = pair_by_clock(poses.spans, stops)
        notes.append(
            f"clock offset: robot clock = tracker clock {pairing.offset:+.3f} s; paired {pairing.paired} "
            f"of {len(poses.spans)} tracker dwells with {len(stops)} robot stops"
        )
    keep = np.array([k for k, p in enumerate(pairing.pairs) if p >= 0], dtype=int)
    unpaired = len(pairing.pairs) - len(keep)
    if unpaired:
        notes.append(
            f"{unpaired} tracker dwells without a robot stop left out (sources "
            + ", ".join(str(poses.sources[k]) for k, p in enumerate(pairing.pairs) if p < 0)[:200]
            + ")"
        )
    return (
        values[[pairing.pairs[k] for k in keep]],
        keep,
        pairing.offset if options.pairing != "order" and timed else None,
    )


def _robot_stops(log: RobotLog, options: ConversionOptions) -> tuple[list[Stretch] | None, np.ndarray]:
    """(time spans of the stops or None, joint values (L, J) of each stop)."""
    if log.spans is not None:
        return [Stretch(k, k + 1, float(a), float(b)) for k, (a, b) in enumerate(log.spans)], log.values
    if log.times is None:
        return None, log.values
    stops = stationary_stretches(log.times, log.values, options.robot_still_speed, options.min_dwell)
    if not stops:
        raise DataFileError(
            log.path,
            f"the robot never stops for {options.min_dwell:g} s (below "
            f"{options.robot_still_speed:g} rad/s: --robot-still-speed, --min-dwell)",
        )
    return stops, np.array([log.values[s.start : s.stop].mean(axis=0) for s in stops])


def _subset(poses: _Poses, keep: np.ndarray) -> _Poses:
    return _Poses(
        poses.positions[keep],
        None if poses.quaternions is None else poses.quaternions[keep],
        poses.joints[keep],
        poses.sources[keep],
        None if poses.scatter is None else poses.scatter[keep],
        None if poses.spans is None else [poses.spans[k] for k in keep],
        None if poses.points is None else poses.points[keep],
    )
