"""Cross-check the radiance SH of each HDR map against Filament's `cmgen` (issue 12, item 8).

For every Radiance .hdr map in --hdri (default ../shared/data/hdri): our SH of the map at
full resolution (pipeline/ibl.py `radiance_sh`: every pixel, exact solid angles; linear RGB
and luminance, 4 bands) against `cmgen --sh=4 --sh-window=no --sh-output=FILE.txt MAP.hdr`
(Filament's tool, Debian package libfilament-tools; the map resampled to a cubemap of
--size pixels per face, 256 by default, then projected). The conventions and how they map
(docs/results/ibl.md, "Agreement with Filament's cmgen"; docs/guides/ibl.md):

- cmgen's coefficients are the radiance projection c_lm = integral L(w) Y_lm(w) dw on the
  real orthonormal basis (the same normalisation as ours: the L00 ratio is 1), ordered
  l(l+1)+m as ours, printed as `(r, g, b); // Llm`;
- in its default output (the cubemap mirrored, as Filament renders it) the odd-m
  coefficients have the opposite sign of ours: cmgen = toggle_condon_shortley(ours), i.e.
  its basis carries the Condon-Shortley phase in our axes (+y up, u = atan2(x, -z) / 2 pi);
  equivalently, our basis in axes turned 180 degrees about z (the two are the same map,
  (-1)^m per coefficient). With --no-mirror the x axis flips as well (a reflection);
- without --sh-irradiance the coefficients are radiance (no cosine lobe); with it they are
  the Ramamoorthi-Hanrahan irradiance E_lm = A_l c_lm (A = pi, 2 pi / 3, pi / 4, 0), no
  1 / pi factor: `sh.irradiance_from_radiance` of ours, compared in the same run;
- windowing: cmgen's default --sh-window=auto windows 3-band SH against ringing (and is off
  for 4 bands); the comparison turns it off (--sh-window=no) for both.

Printed per map: relative L2 error of the 16 luminance coefficients (cmgen mapped by
toggle_condon_shortley against ours), of the 3 x 16 RGB ones, per band, the angle between
the two dominant directions, and the irradiance SH (bands 0-2) of --sh-irradiance against
ours; then the probes: a small bright lobe towards +x, +y, +z and -z, whose band-1 direction
from cmgen (mapped) must point where ours does.

    OPENBLAS_NUM_THREADS=1 NUMBA_NUM_THREADS=1 .venv/bin/python benchmarks/ibl_cmgen.py \\
        [--hdri DIR] [--size 256] [--out ibl_cmgen.json]

Skips with a message (exit 0) when `cmgen` is not on PATH (or at --cmgen).
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from arlight.pipeline import equirect, sh
from arlight.pipeline.color import LUMA
from arlight.pipeline.ibl import angle_deg, radiance_sh

HERE = Path(__file__).resolve().parent
DEFAULT_HDRI = HERE.parents[1] / "shared" / "data" / "hdri"
BANDS = 4
_NUMBER = re.compile(r"[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?")


def read_hdr(path: Path) -> np.ndarray:
    """(H, W, 3) float32 linear RGB of a Radiance .hdr file."""
    bgr = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    if bgr is None:
        raise SystemExit(f"{path}: OpenCV cannot read this .hdr file")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32)


def cmgen_sh(
    cmgen: str, path: Path, size: int, irradiance: bool = False, extra: tuple[str, ...] = ()
) -> tuple[np.ndarray, float]:
    """(3, 16) coefficients cmgen prints for `path` (rows R, G, B), and its wall time, ms."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "sh.txt"
        cmd = [
            cmgen,
            "--quiet",
            f"--sh={BANDS}",
            "--sh-window=no",
            f"--size={size}",
            f"--sh-output={out}",
            *extra,
        ]
        if irradiance:
            cmd.append("--sh-irradiance")
        t0 = time.perf_counter()
        done = subprocess.run([*cmd, str(path)], capture_output=True, text=True, cwd=tmp)
        ms = (time.perf_counter() - t0) * 1e3
        if done.returncode != 0 or not out.exists():
            raise SystemExit(
                f"cmgen failed on {path} (exit {done.returncode}): "
                f"{(done.stderr or done.stdout).strip()[:500]}"
            )
        rows = [
            [float(x) for x in _NUMBER.findall(line.split("//")[0])]
            for line in out.read_text().splitlines()
            if "//" in line
        ]
    coeffs = np.array(rows[: BANDS * BANDS], dtype=np.float64)
    if coeffs.shape != (BANDS * BANDS, 3):
        raise SystemExit(
            f"cmgen's SH output for {path} has shape {coeffs.shape}, expected ({BANDS * BANDS}, 3)"
        )
    return coeffs.T, ms


def to_ours(cmgen_coeffs: np.ndarray) -> np.ndarray:
    """cmgen's default output in our convention: the odd-m coefficients negated."""
    return sh.toggle_condon_shortley(cmgen_coeffs)


def rel_l2(a: np.ndarray, b: np.ndarray) -> float:
    """|a - b| / |b|."""
    return float(np.linalg.norm(np.asarray(a) - b) / max(np.linalg.norm(b), 1e-300))


def compare_map(cmgen: str, path: Path, size: int) -> dict:
    hdr = read_hdr(path)
    t0 = time.perf_counter()
    ours_rgb = radiance_sh(hdr, BANDS)
    ours_ms = (time.perf_counter() - t0) * 1e3
    raw, cmgen_ms = cmgen_sh(cmgen, path, size)
    theirs_rgb = to_ours(raw)
    ours, theirs = LUMA @ ours_rgb, LUMA @ theirs_rgb
    irr_raw, _ = cmgen_sh(cmgen, path, size, irradiance=True)
    ours_irr = sh.irradiance_from_radiance(ours)[:9]
    theirs_irr = (LUMA @ to_ours(irr_raw))[:9]
    per_band = [
        rel_l2(theirs[l * l : (l + 1) ** 2], ours[l * l : (l + 1) ** 2]) for l in range(BANDS)
    ]
    return {
        "map": path.name,
        "size": [hdr.shape[1], hdr.shape[0]],
        "sh_rel_l2": rel_l2(theirs, ours),
        "sh_rgb_rel_l2": rel_l2(theirs_rgb, ours_rgb),
        "sh_rel_l2_unmapped": rel_l2(LUMA @ raw, ours),
        "per_band_rel_l2": per_band,
        "l00_ratio": float(theirs[0] / ours[0]),
        "direction_deg": angle_deg(sh.dominant_direction(theirs), sh.dominant_direction(ours)),
        "irradiance_rel_l2": rel_l2(theirs_irr, ours_irr),
        "ours_ms": ours_ms,
        "cmgen_ms": cmgen_ms,
    }


def probes(cmgen: str, size: int) -> list[dict]:
    """A small bright lobe (exp(30 (d . w - 1))) towards each axis: the band-1 direction of
    cmgen's SH (mapped) against ours, degrees."""
    out = []
    dirs = equirect.pixel_directions(256, 512)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "probe.hdr"
        for name, d in (
            ("+x", (1, 0, 0)),
            ("+y", (0, 1, 0)),
            ("+z", (0, 0, 1)),
            ("-z", (0, 0, -1)),
        ):
            lobe = np.exp(30.0 * (dirs @ np.asarray(d, float) - 1.0)).astype(np.float32)
            image = np.repeat(lobe[..., None], 3, axis=2) + np.float32(0.01)
            cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
            ours = LUMA @ radiance_sh(read_hdr(path), BANDS)
            raw, _ = cmgen_sh(cmgen, path, size)
            mapped = LUMA @ to_ours(raw)
            unmirrored = LUMA @ to_ours(cmgen_sh(cmgen, path, size, extra=("--no-mirror",))[0])
            out.append(
                {
                    "lobe": name,
                    "mapped_deg": angle_deg(
                        sh.dominant_direction(mapped), sh.dominant_direction(ours)
                    ),
                    "unmapped_deg": angle_deg(
                        sh.dominant_direction(LUMA @ raw), sh.dominant_direction(ours)
                    ),
                    "no_mirror_mapped_deg": angle_deg(
                        sh.dominant_direction(unmirrored), sh.dominant_direction(ours)
                    ),
                }
            )
    return out


def _commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, cwd=HERE
        ).stdout.strip()
    except OSError:
        return ""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hdri", type=Path, default=DEFAULT_HDRI)
    ap.add_argument("--cmgen", default=None, help="the cmgen binary (default: on PATH)")
    ap.add_argument(
        "--size",
        type=int,
        default=256,
        help="cmgen's cubemap face size (a power of two; default 256)",
    )
    ap.add_argument("--out", type=Path, help="write every number as JSON")
    args = ap.parse_args(argv)
    cmgen = args.cmgen or shutil.which("cmgen")
    if not cmgen or not Path(cmgen).exists():
        print(
            "ibl_cmgen: skipped: Filament's cmgen is not installed (Debian/Ubuntu: "
            "apt-get install libfilament-tools; or pass --cmgen PATH)"
        )
        return 0
    maps = sorted(args.hdri.glob("*.hdr"))
    if not maps:
        print(f"ibl_cmgen: skipped: no .hdr maps in {args.hdri}")
        return 0
    rows = [compare_map(cmgen, p, args.size) for p in maps]
    print(
        f"cmgen ({cmgen}) --sh=4 --sh-window=no --size={args.size} against radiance_sh "
        "(full resolution), cmgen mapped by toggle_condon_shortley\n"
    )
    print(
        "| map | SH rel. L2 (lum.) | SH rel. L2 (RGB) | unmapped | band 0 / 1 / 2 / 3 "
        "| L00 ratio | direction (deg) | irradiance SH rel. L2 | cmgen ms | ours ms |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        bands = " / ".join(f"{x:.3f}" for x in r["per_band_rel_l2"])
        print(
            f"| {r['map']} | {r['sh_rel_l2']:.4f} | {r['sh_rgb_rel_l2']:.4f} | "
            f"{r['sh_rel_l2_unmapped']:.3f} | {bands} | {r['l00_ratio']:.4f} | "
            f"{r['direction_deg']:.2f} | {r['irradiance_rel_l2']:.4f} | "
            f"{r['cmgen_ms']:.0f} | {r['ours_ms']:.0f} |"
        )
    med = {
        k: float(np.median([r[k] for r in rows]))
        for k in ("sh_rel_l2", "sh_rgb_rel_l2", "direction_deg", "irradiance_rel_l2")
    }
    print(
        f"\nmedian over {len(rows)} maps: SH rel. L2 {med['sh_rel_l2']:.4f} (luminance), "
        f"{med['sh_rgb_rel_l2']:.4f} (RGB); direction {med['direction_deg']:.2f} deg; "
        f"irradiance SH {med['irradiance_rel_l2']:.4f}"
    )
    probe_rows = probes(cmgen, args.size)
    print("\nprobes (a bright lobe towards each axis; band-1 direction, degrees from ours):")
    for p in probe_rows:
        print(
            f"  {p['lobe']}: mapped {p['mapped_deg']:.2f}, unmapped {p['unmapped_deg']:.1f}, "
            f"--no-mirror mapped {p['no_mirror_mapped_deg']:.1f}"
        )
    if args.out:
        args.out.write_text(
            json.dumps(
                {
                    "commit": _commit(),
                    "machine": platform.platform(),
                    "python": sys.version.split()[0],
                    "cmgen": cmgen,
                    "size": args.size,
                    "maps": rows,
                    "median": med,
                    "probes": probe_rows,
                },
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
