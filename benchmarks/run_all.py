"""Run every benchmark in quick mode, one after the other (``make bench``)."""

import pathlib
import subprocess
import sys

HERE = pathlib.Path(__file__).resolve().parent


def main() -> int:
    status = 0
    for script in sorted(HERE.glob("bench_*.py")):
        print(f"=== {script.name} --quick", flush=True)
        status |= subprocess.call([sys.executable, str(script), "--quick"])
    return status


if __name__ == "__main__":
    sys.exit(main())
