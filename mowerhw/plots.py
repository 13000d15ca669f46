"""Figures in the spirit of the paper's (matplotlib, off-screen, small PNGs)."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

import numpy as np

from mowerhw.evaluation.teach import TeachOutcome, horizontal_errors


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def teach_figures(outcome: TeachOutcome, out_dir: str | Path) -> list[Path]:
    """Figs 3, 5 and 7 of the paper for one simulated teach run; returns the files written."""
    plt = _plt()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    run, res, hist = outcome.run, outcome.result, outcome.history
    files = []

    if hist is not None and hist.depth_est:
        # Fig. 3: one landmark's depth and direction converging
        lid = max(hist.depth_est, key=lambda i: len(hist.depth_est[i]))
        rows = np.array(hist.depth_est[lid])
        fig, (a1, a2) = plt.subplots(2, 1, figsize=(6.4, 5.0), sharex=True)
        a1.plot(rows[:, 0], rows[:, 3], ".", ms=3, color="0.6", label="pseudo-measurements (eq. 3)")
        a1.plot(rows[:, 0], rows[:, 2], "b-", label="true")
        a1.plot(rows[:, 0], rows[:, 1], "r-", label="observer estimate")
        a1.set_ylabel("distance (m)")
        a1.set_ylim(0, max(2.0, 1.6 * np.nanmax(rows[:, 2])))
        a1.legend(loc="upper right", fontsize=8)
        a1.set_title(f"Landmark {lid}: depth and direction (cf. paper Fig. 3)", fontsize=10)
        dirs = hist.direction_est[lid]
        td = np.array([d[0] for d in dirs])
        ye = np.array([d[1] for d in dirs])
        yt = np.array([d[2] for d in dirs])
        for c, col in zip(range(3), "rgb", strict=True):
            a2.plot(td, yt[:, c], "--", color=col, lw=1)
            a2.plot(td, ye[:, c], "-", color=col, lw=1, label=f"y_{'xyz'[c]}")
        a2.set_ylabel("unit vector (body)")
        a2.set_xlabel("time (s)")
        a2.legend(loc="upper right", fontsize=8, ncol=3)
        fig.tight_layout()
        files.append(out / "fig3_landmark_depth.png")
        fig.savefig(files[-1], dpi=90)
        plt.close(fig)

    if res is not None:
        # Fig. 5: boundary and map, estimate vs truth
        fig, ax = plt.subplots(figsize=(6.4, 5.6))
        ax.plot(run.truth.xy[:, 0], run.truth.xy[:, 1], "b-", lw=1.5, label="true path")
        b = np.vstack([res.boundary, res.boundary[:1]])
        ax.plot(b[:, 0], b[:, 1], "r-", lw=1, label="taught boundary")
        nc = res.trajectory_no_closure
        ax.plot(nc[:, 1], nc[:, 2], "m:", lw=1, label="filter (no loop closure)")
        ax.plot(run.landmarks_w[:, 0], run.landmarks_w[:, 1], "b*", ms=8, label="true landmarks")
        lm_ids = sorted(res.landmarks)
        est = np.array([res.landmarks[i] for i in lm_ids])
        ax.plot(est[:, 0], est[:, 1], "o", mfc="none", mec="r", ms=8, label="mapped landmarks")
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.legend(fontsize=8, loc="best")
        ax.set_title("Boundary teaching and landmark mapping (cf. paper Fig. 5)", fontsize=10)
        fig.tight_layout()
        files.append(out / "fig5_map.png")
        fig.savefig(files[-1], dpi=90)
        plt.close(fig)

        # Fig. 7: errors over time
        fig, (a1, a2) = plt.subplots(2, 1, figsize=(6.4, 5.0), sharex=True)
        tr = res.trajectory
        idx = np.clip(np.searchsorted(run.truth.t, tr[:, 0] - 1e-9), 0, run.truth.t.size - 1)
        err = tr[:, 1:4] - run.truth.position[idx]
        for c, col in zip(range(3), "rgb", strict=True):
            a1.plot(tr[:, 0], err[:, c], color=col, lw=1, label="xyz"[c])
        a1.plot(nc[:, 0], horizontal_errors(nc, run), "k:", lw=1, label="|xy| no closure")
        a1.set_ylabel("boundary error (m)")
        a1.legend(fontsize=8, ncol=4)
        a1.set_title("Teach-phase errors (cf. paper Fig. 7)", fontsize=10)
        if hist is not None:
            a2.plot(hist.t, hist.landmark_err, "k-", lw=1, label="filter (eq. 20)")
        final = np.mean(np.linalg.norm(est - run.landmarks_w[lm_ids], axis=1))
        a2.axhline(final, color="r", ls="--", lw=1, label=f"final map {final:.3f} m")
        a2.set_ylabel("avg. landmark error (m)")
        a2.set_xlabel("time (s)")
        a2.set_ylim(0, None)
        a2.legend(fontsize=8)
        fig.tight_layout()
        files.append(out / "fig7_errors.png")
        fig.savefig(files[-1], dpi=90)
        plt.close(fig)
    return files


def map_figure(
    lawn_map: Any, path: str | Path, title: str = "", problems: list[str] | None = None
) -> Path:
    """Plot a lawn map: its areas (mowing, navigation), keep-out zones, landmarks, dock;
    ``problems`` (what makes it unfit for mowing) in red over the plot."""
    plt = _plt()
    areas = lawn_map.all_areas()
    big = len(areas) + len(lawn_map.keepouts) > 8
    fig, ax = plt.subplots(figsize=(8.0, 7.2) if big else (6.0, 5.4))
    labelled: set[str] = set()
    for area in areas:  # mowing areas green, navigation areas grey
        b = np.vstack([area.polygon, area.polygon[:1]])
        kind = "mowing area" if area.kind == "mow" else "navigation area"
        fill, edge = ("#cdeccd", "g-") if area.kind == "mow" else ("#e4e4e4", "k--")
        ax.fill(b[:, 0], b[:, 1], color=fill, label=None if kind in labelled else kind)
        ax.plot(b[:, 0], b[:, 1], edge, lw=1.2)
        labelled.add(kind)
        if len(areas) > 1:
            c = area.polygon.mean(axis=0)
            ax.text(c[0], c[1], area.name[:8], ha="center", va="center", fontsize=7, color="g")
    for zone in lawn_map.keepouts:
        z = np.vstack([zone.polygon, zone.polygon[:1]])
        ax.fill(z[:, 0], z[:, 1], color="#f2c0c0")
        ax.plot(z[:, 0], z[:, 1], "r-", lw=1)
        c = zone.polygon.mean(axis=0)
        many = len(lawn_map.keepouts) > 8  # short labels, or the names hide the map
        ax.text(
            c[0],
            c[1],
            zone.name[:6] if many else zone.name,
            ha="center",
            va="center",
            fontsize=6 if many else 8,
        )
    pts = lawn_map.landmark_positions()
    if pts.size:
        ax.plot(pts[:, 0], pts[:, 1], "k^", ms=6, label=f"{pts.shape[0]} landmarks")
    ax.plot(*lawn_map.dock_position[:2], "bs", ms=8, label="dock / teach start")
    way = lawn_map.dock_approach
    if way is not None:
        ax.plot(way[:, 0], way[:, 1], "b-", lw=1.5, label="dock approach")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(fontsize=8, loc="best")
    ax.set_title(title or "Lawn map", fontsize=10)
    if problems:
        text = "UNFIT FOR MOWING:\n" + "\n".join(textwrap.shorten(p, 70) for p in problems[:8])
        ax.text(
            0.02,
            0.98,
            text,
            transform=ax.transAxes,
            va="top",
            fontsize=7,
            color="#b00000",
            bbox={"facecolor": "white", "alpha": 0.85, "edgecolor": "#b00000"},
        )
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def mow_figures(outcome: Any, out_dir: str | Path) -> list[Path]:
    """Figs 6 and 8 of the paper for a simulated mowing run (``evaluate_mow.MowOutcome``)."""
    plt = _plt()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    o = outcome
    files = []
    # Fig. 6: containment while mowing
    fig, ax = plt.subplots(figsize=(6.4, 5.6))
    b = np.vstack([o.true_outline, o.true_outline[:1]])
    ax.plot(b[:, 0], b[:, 1], "k-", lw=0.8, label="true lawn edge")
    mb = np.vstack([o.lawn_map.boundary, o.lawn_map.boundary[:1]])
    ax.plot(mb[:, 0], mb[:, 1], "g-", lw=1.5, label="taught boundary")
    for zone in o.lawn_map.keepouts:
        z = np.vstack([zone.polygon, zone.polygon[:1]])
        ax.fill(z[:, 0], z[:, 1], color="#f2c0c0", label=f"keep-out {zone.name!r}")
    ax.plot(o.true_xy[:, 0], o.true_xy[:, 1], "b-", lw=0.6, label="true path")
    ax.plot(o.est[:, 0], o.est[:, 1], "r-", lw=0.4, alpha=0.8, label="estimated path")
    halted = ~o.permit
    ax.plot(o.est[halted, 0], o.est[halted, 1], ".", ms=2, color="orange", label="deck halted")
    lm = o.lawn_map.landmark_positions()
    ax.plot(lm[:, 0], lm[:, 1], "o", mfc="none", mec="r", ms=7, label="map landmarks")
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(fontsize=7, loc="best")
    ax.set_title("Containment while mowing (cf. paper Fig. 6)", fontsize=10)
    fig.tight_layout()
    files.append(out / "fig6_mowing.png")
    fig.savefig(files[-1], dpi=90)
    plt.close(fig)
    # Fig. 8: pose errors over time, and the permit
    fig, (a1, a2, a3) = plt.subplots(
        3, 1, figsize=(6.4, 6.2), sharex=True, gridspec_kw={"height_ratios": [3, 3, 1]}
    )
    err = o.est[:, :3] - np.column_stack([o.true_xy, np.zeros(len(o.t))])
    for c, col in zip(range(3), "rgb", strict=True):
        a1.plot(o.t, err[:, c], color=col, lw=0.6, label="xyz"[c])
    a1.set_ylabel("location error (m)")
    a1.legend(fontsize=7, ncol=3)
    a1.set_title("Mowing-phase errors (cf. paper Fig. 8)", fontsize=10)
    from mowerhw.common.geometry import yaw_to_quat

    qt = yaw_to_quat(o.true_yaw)
    qe = o.est[:, 3:] * np.sign(np.sum(o.est[:, 3:] * qt, axis=1))[:, None]
    for c, col in zip(range(4), ("k", "r", "g", "b"), strict=True):
        a2.plot(o.t, qe[:, c] - qt[:, c], color=col, lw=0.6, label=f"q{c + 1}")
    a2.set_ylabel("orientation error (quaternion)")
    a2.legend(fontsize=7, ncol=4)
    a3.fill_between(o.t, 0, o.permit.astype(float), step="post", color="g", alpha=0.5)
    a3.set_yticks([0, 1], ["halt", "permit"])
    a3.set_xlabel("time (s)")
    fig.tight_layout()
    files.append(out / "fig8_errors.png")
    fig.savefig(files[-1], dpi=90)
    plt.close(fig)
    return files


def frontend_figures(outcome: Any, out_dir: str | Path, size_px: int = 900) -> list[Path]:
    """Rendered omni frames with the front end's tracks drawn (pixel-level teach run): the
    picture to look at when checking that a camera works. Each track is a dot with its last
    few positions as a trail; green: re-identified with a landmark seen before; orange:
    tracked for a second or more; blue: new. Returns the files written."""
    import cv2

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = []
    for t, (image, tracks, extra) in sorted(outcome.images.items()):
        img = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
        trails, lm_of = extra["trails"], extra["landmark_of"]
        for tid, px, age in zip(tracks.ids.tolist(), tracks.pixels, tracks.ages, strict=True):
            reid = lm_of.get(tid, tid) != tid
            color = (60, 200, 60) if reid else ((0, 150, 255) if age >= 4 else (255, 120, 0))
            pts = np.round(np.asarray(trails.get(tid, [px]))).astype(np.int32)
            if len(pts) > 1:
                cv2.polylines(img, [pts.reshape(-1, 1, 2)], False, color, 2, cv2.LINE_AA)
            cv2.circle(img, (round(float(px[0])), round(float(px[1]))), 7, color, 2, cv2.LINE_AA)
        scale = size_px / img.shape[1]
        small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        label = (
            f"t = {t:.1f} s   {tracks.ids.size} tracks   (rendered 1540x1540, shown {size_px} px)"
        )
        cv2.putText(
            small, label, (12, 28), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2, cv2.LINE_AA
        )
        path = out / f"frontend_t{t:05.1f}.jpg"  # a camera picture: JPEG, not PNG (noise)
        ok, data = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, 88])
        if ok:
            path.write_bytes(data.tobytes())
            files.append(path)
    return files


def recording_figure(recording: str | Path, path: str | Path) -> tuple[Path, str]:
    """One figure of a recording (``mowerhw plot``): where the mower went (estimate, map,
    truth if recorded), containment state and permit over time, sensor rates and gaps.
    Returns the PNG path and the reader's warning (a truncated file is plotted up to the cut).
    """
    import json as _json

    from mowerhw.map import from_document
    from mowerhw.recording.mcap import RecordingRead

    rd = RecordingRead(recording)
    times: dict[str, list[float]] = {}
    est: list[tuple[float, float, float]] = []
    truth: list[tuple[float, float, float]] = []
    states: list[tuple[float, str, bool]] = []
    unreadable = 0
    for topic, log_ns, msg in rd.messages():
        t = log_ns * 1e-9
        times.setdefault(topic, []).append(t)
        try:
            if topic == "/estimate/pose":
                p = msg["pose"]["position"]
                est.append((t, float(p["x"]), float(p["y"])))
            elif topic == "/truth/pose":
                p = msg["pose"]["position"]
                truth.append((t, float(p["x"]), float(p["y"])))
            elif topic == "/estimate/state":
                states.append((t, str(msg["state"]), bool(msg["permit"])))
        except (KeyError, TypeError, ValueError):  # a damaged message: skipped, counted
            unreadable += 1
    if unreadable:
        rd.warning += f"{'; ' if rd.warning else ''}{unreadable} message(s) unreadable, skipped"
    if not times:
        raise ValueError(f"{recording}: no messages ({rd.warning or 'empty recording'})")
    t0 = min(v[0] for v in times.values())
    plt = _plt()
    fig = plt.figure(figsize=(12, 8))
    gs = fig.add_gridspec(3, 2, width_ratios=[1.1, 1.4])
    ax_map = fig.add_subplot(gs[:, 0])
    ax_state = fig.add_subplot(gs[0, 1])
    ax_rate = fig.add_subplot(gs[1, 1], sharex=ax_state)
    ax_gap = fig.add_subplot(gs[2, 1], sharex=ax_state)
    map_data = rd.attachments.get("map.json")
    if map_data:
        lawn_map = from_document(_json.loads(map_data), "recorded map")
        b = np.vstack([lawn_map.boundary, lawn_map.boundary[:1]])
        ax_map.fill(b[:, 0], b[:, 1], color="#cdeccd", label="lawn (map)")
        ax_map.plot(b[:, 0], b[:, 1], "g-", lw=1.2)
        pts = lawn_map.landmark_positions()
        if pts.size:
            ax_map.plot(pts[:, 0], pts[:, 1], "k^", ms=3, label=f"{len(pts)} landmarks")
    if truth:
        a = np.array(truth)
        ax_map.plot(a[:, 1], a[:, 2], "-", color="0.6", lw=1.0, label="truth")
    if est:
        a = np.array(est)
        ax_map.plot(a[:, 1], a[:, 2], "b-", lw=0.8, label="estimate")
    ax_map.set_aspect("equal")
    ax_map.set_xlabel("x (m)")
    ax_map.set_ylabel("y (m)")
    ax_map.legend(fontsize=8, loc="best")
    ax_map.set_title("trajectory and map", fontsize=10)
    if states:
        codes = {"INSIDE": 0, "NEAR_EDGE": 1, "OUTSIDE": 2, "UNKNOWN": 3, "TEACH": 4}
        a_t = np.array([s[0] - t0 for s in states])
        a_c = np.array([codes.get(s[1], 3) for s in states])
        a_p = np.array([s[2] for s in states])
        ax_state.step(a_t, a_c, where="post", color="k", lw=0.8)
        ax_state.fill_between(
            a_t,
            -0.5,
            4.5,
            where=a_p,
            step="post",
            color="#b7e4b7",
            alpha=0.6,
            label="mowing permitted",
        )
        ax_state.set_yticks(list(codes.values()), list(codes))
        ax_state.legend(fontsize=8, loc="upper right")
    ax_state.set_title("containment state and permit", fontsize=10)
    for topic, ts in sorted(times.items()):
        if topic.startswith("/estimate") or topic.startswith("/truth"):
            continue
        a = np.asarray(ts) - t0
        edges = np.arange(0.0, a[-1] + 1.0, 1.0)
        if edges.size < 2:
            continue
        counts, _ = np.histogram(a, edges)
        ax_rate.step(edges[:-1], counts, where="post", lw=0.8, label=topic)
        gaps = np.diff(a)
        if gaps.size:
            ax_gap.plot(a[1:], gaps * 1e3, ".", ms=2, label=topic)
    ax_rate.set_ylabel("messages / s")
    ax_rate.legend(fontsize=7, loc="upper right")
    ax_rate.set_title("sensor rates", fontsize=10)
    ax_gap.set_yscale("log")
    ax_gap.set_ylabel("gap to previous (ms)")
    ax_gap.set_xlabel("time since start of recording (s)")
    ax_gap.set_title("gaps (a stale sensor shows as a spike)", fontsize=10)
    title = f"{Path(recording).name}"
    if rd.warning:
        title += "  (truncated: plotted up to the cut)"
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out, rd.warning
