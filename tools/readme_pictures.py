"""Regenerates the README's pictures (the paper's three views) from the current demo.

    python tools/readme_pictures.py                    # runs `panosfm demo` into /tmp/panosfm-readme-demo
    python tools/readme_pictures.py --demo out/demo    # reuses (and completes) an existing demo folder

Runs :func:`panosfm_graph.pipeline.run_demo` with its defaults (the same capture and settings as
``panosfm demo``; cached stages are reused), copies ``reconstruction/views/{quarter,height,topdown}.png``
to ``docs/images/`` and writes ``docs/images/demo.json``: the demo's registered frames and its metrics
against the ground truth, so the README's caption can be checked against the pictures.
"""
from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
VIEWS = ("quarter", "height", "topdown")


def regenerate(demo_dir: Path, images_dir: Path = ROOT / "docs" / "images") -> dict:
    """Returns the demo's caption figures after copying its three views into ``images_dir``."""
    from panosfm_graph.export import to_jsonable
    from panosfm_graph.pipeline import run_demo

    result = run_demo(demo_dir)
    images_dir.mkdir(parents=True, exist_ok=True)
    for name in VIEWS:
        shutil.copyfile(result.out_dir / "views" / f"{name}.png", images_dir / f"{name}.png")
    metrics = result.summary.get("eval", {})
    frames = result.summary["frames"]
    caption = {"frames": {k: frames[k] for k in ("total", "registered")}, "eval": metrics}
    (images_dir / "demo.json").write_text(json.dumps(to_jsonable(caption), indent=2) + "\n")
    return caption


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--demo", type=Path, default=Path("/tmp/panosfm-readme-demo"),
                    help="demo folder (created or reused)")
    ap.add_argument("--images", type=Path, default=ROOT / "docs" / "images", help="where the PNGs go")
    args = ap.parse_args()
    caption = regenerate(args.demo, args.images)
    frames = caption["frames"]
    print(f"wrote {', '.join(f'{n}.png' for n in VIEWS)} to {args.images}; "
          f"registered {frames.get('registered')}/{frames.get('total')}")


if __name__ == "__main__":
    main()
