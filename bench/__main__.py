"""`python -m bench [PART ...] [-- ARGS]`: runs benchmark parts in turn, each in its own process so one failure or
crash does not stop the others, and says which ones ran. Each part writes bench/results/<part>.json;
afterwards bench/results.json gathers every part's results file that exists into one document, with
when each part last ran here, with which arguments and how it ended (parts not run this time keep
their earlier entry; a part that ran without writing a file, such as cuda on a machine without a GPU,
has "file": null).
ARGS after `--` go to the one part named (`python -m bench fit -- --presets fast`)."""
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PARTS = ("kernels", "step_parts", "background", "poses", "normalize", "fit", "scaling", "scene_models", "real_scenes",
         "sfm_captures", "grid_ceiling", "export", "object_captures", "cuda",
         "protocol", "lpips_reference", "peers", "faults")
COMBINED = REPO / "bench" / "results.json"


def combine(outcomes: list[tuple[str, int, float, str, list[str]]]) -> None:
    """Rewrites bench/results.json from the parts' files, recording this invocation's outcomes."""
    sys.path.insert(0, str(REPO))
    from bench.fit import machine

    earlier = json.loads(COMBINED.read_text()).get("parts", {}) if COMBINED.is_file() else {}
    ran = {part: {"exit_code": code, "seconds": round(seconds, 1), "finished": finished, "args": args}
           for part, code, seconds, finished, args in outcomes}
    parts = {}
    for part in PARTS:
        path = REPO / "bench" / "results" / f"{part}.json"
        last_run = ran.get(part, earlier.get(part, {}).get("last_run"))
        if path.is_file() or last_run:
            parts[part] = {"file": str(path.relative_to(REPO)) if path.is_file() else None, "last_run": last_run,
                           "results": json.loads(path.read_text()) if path.is_file() else None}
    COMBINED.write_text(json.dumps({"machine": machine(), "parts": parts}, indent=1) + "\n")


def main(argv: list[str]) -> int:
    part_args = argv[argv.index("--") + 1:] if "--" in argv else []
    parts = (argv[:argv.index("--")] if "--" in argv else argv) or list(PARTS)
    unknown = [p for p in parts if p not in PARTS]
    if unknown:
        print(f"error: unknown benchmark part {unknown[0]}; parts are: {', '.join(PARTS)}", file=sys.stderr)
        return 2
    if part_args and len(parts) != 1:
        print("error: arguments after -- go to one part; name exactly one (for example: fit -- --presets fast)",
              file=sys.stderr)
        return 2
    outcomes = []
    for part in parts:
        started = time.time()
        code = subprocess.call([sys.executable, "-m", f"bench.{part}", *part_args], cwd=REPO)
        outcomes.append((part, code, time.time() - started, time.strftime("%Y-%m-%dT%H:%M:%S%z"), part_args))
    for part, code, seconds, _, _ in outcomes:
        print(f"[bench] {part:<13} {'ok' if code == 0 else f'exit {code}':<8} {seconds:7.1f} s")
    combine(outcomes)
    print(f"[bench] wrote {COMBINED.relative_to(REPO)}")
    return 0 if all(code == 0 for _, code, _, _, _ in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
