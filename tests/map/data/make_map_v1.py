"""Write ``map_v1.db.gz``: a map in the layout planarloc wrote before compact maps (git 5f224cc).

Run with that version of planarloc on the path (``git archive 5f224cc | tar -x -C /tmp/v1``)::

    PYTHONPATH=/tmp/v1:tests/support python tests/map/data/make_map_v1.py tests/map/data

It builds a 4-image map of generated textured images (``posed_folder``, seed 0) and records
SHA-256 digests of what that version decodes (features, global descriptors) in
``map_v1.json``, so that ``tests/map/test_codec.py`` can check that today's reader returns
exactly the same arrays.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import shutil
import sys
import tempfile
from pathlib import Path

from posed_folder import posed_folder

from planarloc.map.builder import build_map
from planarloc.map.store import MapDatabase


def main(out: Path) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        images = posed_folder(Path(tmp) / "data", n=4, seed=0)
        path = build_map(images, Path(tmp) / "map_v1.db", num_words=8)
        record = {"images": {}}
        with MapDatabase.open(path) as db:
            for name in db.image_names():
                f = db.get_features(name)
                record["images"][name] = {
                    "num": len(f),
                    "sha256": {
                        k: hashlib.sha256(getattr(f, k).tobytes()).hexdigest()
                        for k in ("keypoints", "descriptors", "scales")
                    },
                }
            ids, g = db.get_global_descriptors()
            record["global"] = {
                "ids": ids.tolist(),
                "shape": list(g.shape),
                "sha256": hashlib.sha256(g.tobytes()).hexdigest(),
            }
        with open(path, "rb") as src, gzip.open(out / "map_v1.db.gz", "wb", compresslevel=9) as dst:
            shutil.copyfileobj(src, dst)
        (out / "map_v1.json").write_text(json.dumps(record, indent=1) + "\n")


if __name__ == "__main__":
    main(Path(sys.argv[1]))
