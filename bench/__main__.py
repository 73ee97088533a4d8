"""`python -m bench [PART ...]`: runs benchmark parts in turn, each in its own process so one failure or
crash does not stop the others, and says which ones ran. Results: bench/results/<part>.json."""
import subprocess
import sys
import time
from pathlib import Path

PARTS = ("kernels", "poses", "normalize", "fit", "scene_models", "export", "cuda")


def main(argv: list[str]) -> int:
    parts = argv or list(PARTS)
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        print(f"error: unknown benchmark part {unknown[0]}; parts are: {', '.join(PARTS)}", file=sys.stderr)
        return 2
    outcomes = []
    for part in parts:
        started = time.time()
        code = subprocess.call([sys.executable, "-m", f"bench.{part}"], cwd=Path(__file__).resolve().parent.parent)
        outcomes.append((part, code, time.time() - started))
    for part, code, seconds in outcomes:
        print(f"[bench] {part:<13} {'ok' if code == 0 else f'exit {code}':<8} {seconds:7.1f} s")
    return 0 if all(code == 0 for _, code, _ in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
