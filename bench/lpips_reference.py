"""LPIPS against its reference: stages/scoring/lpips.py on the LPIPS repository's example images, beside the values
lpips v0.1 (AlexNet) gives for them, and the installed linear heads beside the repository's own v0.1 `alex.pth`.

Needs a checkout of github.com/richzhang/PerceptualSimilarity (--repo: imgs/ex_ref.png, ex_p0.png, ex_p1.png
and lpips/weights/v0.1/alex.pth); without one it says so and writes nothing.

    .venv/bin/python -m bench.lpips_reference --repo ../PerceptualSimilarity
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

RESULTS = REPO / "bench" / "results" / "lpips_reference.json"
# lpips v0.1, AlexNet: d(ex_ref, ex_p0) and d(ex_ref, ex_p1) to 3 decimals, the published values for those images.
EXPECTED = {"ex_p0": 0.722, "ex_p1": 0.138}


def main(argv=None) -> int:
    import imageio.v3 as iio
    import torch

    from stages.scoring import lpips

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repo", type=Path, help="a checkout of richzhang/PerceptualSimilarity")
    parser.add_argument("--results", type=Path, default=RESULTS)
    args = parser.parse_args(argv)
    images = args.repo / "imgs" if args.repo else None
    if images is None or not (images / "ex_ref.png").is_file():
        print("bench.lpips_reference: no LPIPS example images (pass --repo, a checkout of "
              "richzhang/PerceptualSimilarity); nothing measured", file=sys.stderr)
        return 0
    ref = iio.imread(images / "ex_ref.png")[..., :3]
    distances = {name: lpips.image_lpips(ref, iio.imread(images / f"{name}.png")[..., :3]) for name in EXPECTED}
    heads = None
    pth = args.repo / "lpips" / "weights" / "v0.1" / "alex.pth"
    if pth.is_file():
        state = torch.load(pth, map_location="cpu", weights_only=True)
        net = lpips.load_lpips()
        heads = [float((state[f"lin{i}.model.1.weight"].flatten() - net.heads[i]).abs().max()) for i in range(5)]
    result = {"distances": {k: round(v, 5) for k, v in distances.items()}, "expected": EXPECTED,
              "match_to_3_decimals": all(round(distances[k], 3) == v for k, v in EXPECTED.items()),
              "heads_max_abs_difference_vs_alex_pth": heads, "finished": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
    for name, value in distances.items():
        print(f"  d(ex_ref, {name}) = {value:.4f}  (lpips v0.1: {EXPECTED[name]:.3f})")
    if heads is not None:
        print(f"  linear heads vs alex.pth: max |difference| {max(heads):.3g}")
    args.results.parent.mkdir(parents=True, exist_ok=True)
    args.results.write_text(json.dumps(result, indent=1) + "\n")
    return 0 if result["match_to_3_decimals"] else 1


if __name__ == "__main__":
    sys.exit(main())
