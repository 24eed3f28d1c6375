#!/usr/bin/env python
"""`uhrnet bench` as a pipeline benchmark: writes its JSON (default out/bench/uhrnet.json).

    python pipelines/bench_uhrnet.py [--out FILE] [any uhrnet bench option, e.g. --optimize --repeats 3]
"""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main(argv=None) -> int:
    from uhrnet.cli import main as uhrnet_main

    argv = list(sys.argv[1:] if argv is None else argv)
    out = ROOT / "out" / "bench" / "uhrnet.json"
    if "--out" in argv:
        i = argv.index("--out")
        out = Path(argv[i + 1])
        del argv[i : i + 2]
    return uhrnet_main(["bench", *argv, "--json", str(out)])


if __name__ == "__main__":
    sys.exit(main())
