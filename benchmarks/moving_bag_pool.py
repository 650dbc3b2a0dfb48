"""The waved-board bags of every moving-bag page pooled (make bench, after the pages it reads; `python
benchmarks/moving_bag_pool.py [--pages docs/bench]`): the offset's and the extrinsic's errors and the NEES over all
the bags the pages hold, read back from each page's per-bag table (``bench_moving_bag.py``'s output, written
unedited by ``record.py``), so that runs of a few dozen bags each add up to one figure.

Printed: the bags and the pages they come from, the offset error (RMS, largest), the extrinsic's error (RMS of the
rotation and of the translation), the NEES of the extrinsic and the offset together (7 dof: mean, the standard
deviation of the mean, and the share beyond the chi-square's 95% and 99% points), the verdicts; and the same by
LiDAR and by time field. A seed on two pages is an error (a bag counted twice).
"""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import numpy as np
from scipy.stats import chi2

ROOT = Path(__file__).resolve().parents[1]
HEADER = "| seed | LiDAR | field | s | m/s | deg/s | offset ms | error ms | deg | mm | NEES | verdict |"


def read_page(path: Path) -> list[dict]:
    """The per-bag rows of one page (an empty list where it has none)."""
    lines = path.read_text().splitlines()
    if HEADER not in lines:
        return []
    rows = []
    for line in lines[lines.index(HEADER) + 2:]:
        if not re.match(r"^\| \d+ \|", line):
            break
        c = [x.strip() for x in line.strip("|").split("|")]
        rows.append({"seed": int(c[0]), "lidar": c[1], "field": c[2], "offset_err_ms": float(c[7]),
                     "rot_deg": float(c[8]), "trans_mm": float(c[9]), "nees": float(c[10]), "verdict": c[11],
                     "page": path.name})
    return rows


def page_bound(path: Path) -> tuple[float, float, float, float] | None:
    """A page's RMS rotation (deg) and translation (mm) errors and its errors' ratios to the continuous model's
    bound (the rows of its summary table), or None where it has not them."""
    text = path.read_text()
    rot = re.search(r"^\| rotation error, RMS \| ([\d.]+) deg", text, re.M)
    trans = re.search(r"^\| translation error, RMS \| ([\d.]+) mm", text, re.M)
    ratio = re.search(r"^\| RMS error / the continuous model's bound \| rotation ([\d.]+), translation ([\d.]+)",
                      text, re.M)
    if not (rot and trans and ratio):
        return None
    return float(rot.group(1)), float(trans.group(1)), float(ratio.group(1)), float(ratio.group(2))


def page_pointing(path: Path) -> dict[float, float]:
    """A page's mean NEES were the camera's pointing term another size (px -> mean NEES), or empty."""
    row = re.search(r"^\| NEES were the camera's pointing term \(px\) another size, mean \| ([^|]+)\|",
                    path.read_text(), re.M)
    return {float(a): float(b) for a, b in re.findall(r"([\d.]+): ([\d.]+)", row.group(1))} if row else {}


def pooled_ratio(parts: list[tuple[int, float, float]]) -> float:
    """``sqrt(sum n e^2 / sum n (e / q)^2)`` over pages of ``n`` bags, RMS error ``e`` and ratio ``q``: the pooled
    RMS error over the pooled RMS bound."""
    return float(np.sqrt(sum(n * e ** 2 for n, e, _ in parts) / sum(n * (e / q) ** 2 for n, e, q in parts)))


def rms(x) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def summary(rows: list[dict]) -> str:
    nees = np.array([r["nees"] for r in rows])
    err = np.array([r["offset_err_ms"] for r in rows])
    sd = nees.std(ddof=1) / np.sqrt(len(nees)) if len(nees) > 1 else float("nan")
    return (f"| {len(rows)} | {rms(err):.2f} | {np.abs(err).max():.2f} | {rms([r['rot_deg'] for r in rows]):.3f} | "
            f"{rms([r['trans_mm'] for r in rows]):.1f} | {nees.mean():.1f} ({sd:.1f}) | "
            f"{np.mean(nees > chi2.ppf(0.95, 7)):.0%} | {np.mean(nees > chi2.ppf(0.99, 7)):.0%} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pages", default=str(ROOT / "docs" / "bench"))
    a = ap.parse_args()
    pages = sorted(Path(a.pages).glob("moving_bag*.md"))
    rows, seen = [], {}
    for page in pages:
        for r in read_page(page):
            if r["seed"] in seen:
                sys.exit(f"{page}: seed {r['seed']} is also on {seen[r['seed']]}: a bag would count twice; rerun one "
                         "of the two pages with other seeds")
            seen[r["seed"]] = page.name
            rows.append(r)
    if not rows:
        sys.exit(f"{a.pages}: no moving-bag page with a per-bag table; run bench_moving_bag.py through record.py first")
    print(f"{len(rows)} simulated bags (offset free), seeds {min(seen)}..{max(seen)} ({len(seen)} distinct), "
          "pooled from:\n")
    for page in pages:
        mine = [r["seed"] for r in rows if r["page"] == page.name]
        if mine:
            run = re.search(r"^- run: (.*)$", page.read_text(), re.M)
            print(f"- {page.name}: {len(mine)} bags, seeds {min(mine)}..{max(mine)}; {run.group(1) if run else ''}")
    print()
    head = ("| bags | offset error RMS (ms) | largest (ms) | rotation RMS (deg) | translation RMS (mm) | "
            "NEES mean (sd of the mean; 7 if honest) | NEES > chi2(7) 95% | > 99% |")
    rule = "|---" * 8 + "|"
    print(head.replace("| bags |", "| | bags |"))
    print(rule + "---|")
    print("| all " + summary(rows))
    for key in ("lidar", "field"):
        for value in sorted({r[key] for r in rows}):
            print(f"| {key} {value} " + summary([r for r in rows if r[key] == value]))
    bounds = [(sum(r["page"] == p.name for r in rows), page_bound(p)) for p in pages]
    bounds = [(n, b) for n, b in bounds if n and b is not None]
    if bounds:
        covered = sum(n for n, _ in bounds)
        print(f"\nRMS error / the continuous model's bound, pooled over the {covered} bags whose pages give both "
              f"(each page's RMS bound read back from its RMS error and its ratio): rotation "
              f"{pooled_ratio([(n, b[0], b[2]) for n, b in bounds]):.2f}, translation "
              f"{pooled_ratio([(n, b[1], b[3]) for n, b in bounds]):.2f} (1 for an efficient estimate; target 1.2)")
    pointing = [(sum(r["page"] == p.name for r in rows), page_pointing(p)) for p in pages]
    pointing = [(n, d) for n, d in pointing if n and d]
    sizes = sorted(set.intersection(*(set(d) for _, d in pointing))) if pointing else []
    if sizes:
        covered = sum(n for n, _ in pointing)
        print(f"\nNEES mean were the camera's pointing term another size, pooled over the {covered} bags whose pages "
              "give it (the same estimates, only the covariance differs): " + ", ".join(
                  f"{px:g} px: {sum(n * d[px] for n, d in pointing) / covered:.2f}" for px in sizes))
    print("\nverdicts: " + ", ".join(f"{k} {sum(r['verdict'] == k for r in rows)}"
                                     for k in ("OK", "CHECK", "UNTRUSTED")))


if __name__ == "__main__":
    main()
