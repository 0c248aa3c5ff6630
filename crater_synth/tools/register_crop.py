"""``python -m crater_synth.tools.register_crop [--out DIR] [--check]``: rebuild (or check) the embedded
real LOLA crop around Shackleton (data_manifest/embedded/shackleton_lola_200m) with
:mod:`crater_synth.terrain.register`.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from crater_synth.errors import UserError
from crater_synth.terrain.dem import Dem
from crater_synth.terrain.register import PRODUCT_DIR, build_shackleton
from data_manifest.products import resolve_product


def main(argv: list[str] | None = None) -> int:
    """``python -m crater_synth.tools.register_crop [--out DIR] [--check]``."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--src", type=Path, default=PRODUCT_DIR, help="folder holding the source EXRs")
    ap.add_argument("--out", type=Path, default=PRODUCT_DIR, help="folder to write the products into")
    ap.add_argument("--check", action="store_true", help="rebuild in a temp folder and compare with --out")
    ap.add_argument("--data-dir", default="data")
    args = ap.parse_args(argv)
    try:
        ref = Dem(resolve_product("lola_ldem256_south", args.data_dir), product="lola_ldem256_south")
        if not args.check:
            doc = build_shackleton(args.src, args.out, ref)
            print(json.dumps({"registration": doc["registration"], "outputs": doc["outputs"]}, indent=1))
            return 0
        with tempfile.TemporaryDirectory() as tmp:
            doc = build_shackleton(args.src, Path(tmp), ref)
        committed = json.loads((args.out / "registration.json").read_text(encoding="utf-8"))
        same = committed["outputs"] == doc["outputs"]
        print(json.dumps({"identical": same, "rebuilt": doc["outputs"], "committed": committed["outputs"]}))
        return 0 if same else 1
    except (UserError, ValueError, OSError) as exc:
        print(f"error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
