"""Contact sheets of a dome and a dense scene for docs/benchmark.md.

.venv/bin/python bench/contact_sheets.py
"""

from __future__ import annotations

import json

from common import DOCS, OUT, setup_logging

from colmap_vc.synthetic import SynthOptions, generate
from colmap_vc.viz import contact_sheet


def main() -> None:
    setup_logging()
    for preset, people in (("dome", 3), ("dense", 1)):
        scene = OUT / "scenes" / f"sheet_{preset}"
        generate(
            preset,
            scene,
            SynthOptions(
                seed=0,
                num_people=people,
                num_cameras=12,
                make_database=False,
                overwrite=True,
            ),
        )
        spec = json.loads((scene / "scene.json").read_text())
        names = [c["name"] for c in spec["cameras"]]
        contact_sheet(
            [scene / "images" / n for n in names],
            DOCS / "img" / f"{preset}_contact.png",
            columns=4,
            tile_width=240,
            title=f"colmap-vc synth {preset} --seed 0 --people {people} --cameras 12",
        )


if __name__ == "__main__":
    main()
