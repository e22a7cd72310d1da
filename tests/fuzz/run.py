"""Run every fuzz harness (``make fuzz``) and write ``fuzz-out/fuzz.json``.

``python tests/fuzz/run.py --runs N --seconds S [--out fuzz-out] [--engine atheris|mutate] [reader ...]``

Each reader's harness (``tests/fuzz/fuzz_<reader>.py``) runs in its own process for at most
``--runs`` executions or ``--seconds`` seconds (per reader), with atheris (coverage guided) when it
is installed, else the seeded random-mutation fuzzer of :mod:`tests.fuzz.common`. The summary lists,
per reader: executions, seconds, unique crashes (by exception type and innermost package frame) and
one reproducer file each. Exit status 1 when any reader crashed.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))
from tests.fuzz.common import READERS  # noqa: E402


def run_one(name: str, args, out: Path) -> dict:
    stats = out / name / "stats.json"
    stats.unlink(missing_ok=True)
    cmd = [sys.executable, str(HERE / f"fuzz_{name}.py"), "--runs", str(args.runs), "--seconds", str(args.seconds),
           "--out", str(out)] + (["--engine", args.engine] if args.engine else [])
    log = out / name / "fuzz.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "wb") as fh:
        proc = subprocess.run(cmd, stdout=fh, stderr=subprocess.STDOUT, timeout=args.seconds * 2 + 120,
                              env={**os.environ, "PYTHONUNBUFFERED": "1"})
    result = json.loads(stats.read_text()) if stats.is_file() else {"reader": name, "executions": 0, "seconds": 0,
                                                                      "unique_crashes": 0, "crashes": []}
    text = log.read_text(errors="replace")
    died = re.search(r"ERROR: libFuzzer: (\S+)", text)
    if died:  # out-of-memory, timeout, deadly signal: libFuzzer stops there and keeps the input
        unit = re.search(r"Test unit written to (\S+)", text)
        result["crashes"].append({"key": f"{died.group(1)} (libFuzzer)", "type": died.group(1),
                                  "message": "", "reproducer": unit.group(1) if unit else None})
        result["unique_crashes"] = len(result["crashes"])
    done = re.search(r"^Done (\d+) runs in (\d+) second", text, re.M)
    units = re.findall(r"^stat::number_of_executed_units: (\d+)", text, re.M)
    if not done and units:  # libFuzzer stopped on an error: its count so far
        result["executions"] = int(units[-1])
    if done:  # atheris ends the process without a last flush: libFuzzer's own count is exact
        result["executions"], result["seconds"] = int(done.group(1)), max(float(done.group(2)), result["seconds"])
    if proc.returncode != 0 and not result["crashes"]:
        result["crashes"].append({"key": f"fuzzer exited {proc.returncode} (see {log})", "type": "exit",
                                  "message": "", "reproducer": None})
        result["unique_crashes"] = len(result["crashes"])
    return result


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("readers", nargs="*", help=f"default: all ({', '.join(READERS)})")
    ap.add_argument("--runs", type=int, default=1_000_000)
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=Path("fuzz-out"))
    ap.add_argument("--engine", choices=("atheris", "mutate"), default=None)
    args = ap.parse_args()
    out = args.out.resolve()
    results = []
    for name in args.readers or list(READERS):
        r = run_one(name, args, out)
        results.append(r)
        print(f"{name:16s} {r['executions']:>9d} runs {r['seconds']:>7.1f} s {r['unique_crashes']:>3d} crash(es)",
              flush=True)
        for c in r["crashes"]:
            print(f"    {c['key']}: {c['message'][:120]!r} -> {c['reproducer']}", flush=True)
    (out / "fuzz.json").write_text(json.dumps({"runs": args.runs, "seconds": args.seconds, "readers": results},
                                              indent=1))
    print(f"wrote {out / 'fuzz.json'}")
    return 1 if any(r["unique_crashes"] for r in results) else 0


if __name__ == "__main__":
    sys.exit(main())
