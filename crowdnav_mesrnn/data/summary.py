"""Per-recording and per-split counts printed by ``crowdnav-mesrnn data summary``."""

from __future__ import annotations

import os
from typing import Any

from crowdnav_mesrnn.data.constants import PARTS, RECORDINGS, SPLITS, split_recordings
from crowdnav_mesrnn.data.paths import find_data_dir
from crowdnav_mesrnn.data.recordings import load_recording
from crowdnav_mesrnn.data.windows import windows_from_recording


def data_summary(data_dir: str | os.PathLike[str] | None = None) -> dict[str, Any]:
    """Frames, pedestrians, rows, step time and window counts (all, and with >= 2 scored)."""
    root = find_data_dir(data_dir)
    recs: dict[str, Any] = {}
    for name in RECORDINGS:
        rec = load_recording(name, "all_data", root)
        wins = windows_from_recording(rec, min_scored=0)
        recs[name] = {
            "frames": len(rec.frames),
            "pedestrians": len(rec.ped_ids),
            "rows": rec.num_rows,
            "step_s": round(rec.step_s, 4),
            "duration_s": round(float(rec.times_s()[-1]), 2),
            "windows": len(wins),
            "windows_min2": sum(w.num_scored >= 2 for w in wins),
        }
    splits: dict[str, Any] = {}
    for split in SPLITS:
        splits[split] = {}
        for part in PARTS:
            frames = peds = n_all = n_min2 = 0
            files = []
            for name, folder in split_recordings(split, part):
                rec = load_recording(name, folder, root)
                wins = windows_from_recording(rec, min_scored=0)
                frames += len(rec.frames)
                peds += len(rec.ped_ids)
                n_all += len(wins)
                n_min2 += sum(w.num_scored >= 2 for w in wins)
                files.append(rec.name)
            splits[split][part] = {
                "files": files,
                "frames": frames,
                "pedestrians": peds,
                "windows": n_all,
                "windows_min2": n_min2,
            }
    return {"data_dir": str(root), "recordings": recs, "splits": splits}


def format_summary(summary: dict[str, Any]) -> str:
    """Plain-text tables of :func:`data_summary`."""
    lines = [f"ETH/UCY data in {summary['data_dir']}", ""]
    hdr = f"{'recording':<16}{'frames':>8}{'peds':>7}{'rows':>8}{'step_s':>8}{'windows':>9}{'>=2 scored':>12}"
    lines += [hdr, "-" * len(hdr)]
    for name, r in summary["recordings"].items():
        lines.append(
            f"{name:<16}{r['frames']:>8}{r['pedestrians']:>7}{r['rows']:>8}{r['step_s']:>8.3f}"
            f"{r['windows']:>9}{r['windows_min2']:>12}"
        )
    lines += ["", f"{'split':<8}{'part':<7}{'files':>6}{'frames':>8}{'peds':>7}{'windows':>9}{'>=2 scored':>12}"]
    lines.append("-" * 57)
    for split, parts in summary["splits"].items():
        for part, p in parts.items():
            lines.append(
                f"{split:<8}{part:<7}{len(p['files']):>6}{p['frames']:>8}{p['pedestrians']:>7}"
                f"{p['windows']:>9}{p['windows_min2']:>12}"
            )
    return "\n".join(lines)
