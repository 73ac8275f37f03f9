"""hdmap.geo.signs: classes by wire code, name and OSM value; a deployment's catalogue file
adding classes and sizes; ingest accepting the classes of its catalogue and naming the
code of a row it refuses."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from fleetsim.synthetic import make_observations
from hdmap.geo.signs import (
    CATALOG,
    SignCatalog,
    SignCatalogError,
    SignClass,
    UnknownSignClass,
)
from hdmap.runtime.config import ConfigError
from hdmap.runtime.service import Item, ServiceOptions
from schemas import ObservationBatch, keys
from services.ingest.service import IngestConfig, IngestService

ROOT = Path(__file__).resolve().parents[2]

# The catalogue before OSM values were added: codes, names and panel heights are the
# wire contract and every evaluation's input, so they must not move.
BEFORE = [
    (1, "stop", 0.75),
    (2, "give_way", 0.78),
    (3, "no_entry", 0.64),
    (4, "speed_limit_30", 0.64),
    (5, "speed_limit_40", 0.64),
    (6, "speed_limit_50", 0.64),
    (7, "no_parking", 0.64),
    (8, "no_stopping", 0.64),
    (9, "pedestrian_crossing", 0.64),
    (10, "priority_road", 0.64),
    (11, "one_way", 0.64),
    (12, "parking", 0.64),
    (13, "roundabout", 0.64),
    (14, "keep_right", 0.64),
    (15, "children", 0.78),
    (16, "road_works", 0.78),
    (17, "bus_stop", 0.64),
    (18, "no_turn", 0.64),
    (19, "cycle_path", 0.64),
    (20, "dead_end", 0.64),
]

DE_CLASS = """
[[class]]
code = 1000
name = "de_priority_road"
osm = "DE:306"
height_m = 0.6
size_rel_sigma = 0.05
"""


def test_defaults_are_unchanged() -> None:
    assert [(c.code, c.name, c.height_m) for c in CATALOG] == BEFORE
    assert {c.size_rel_sigma for c in CATALOG} == {0.10}
    np.testing.assert_array_equal(CATALOG.codes, np.arange(1, 21))
    np.testing.assert_allclose(
        CATALOG.heights(np.arange(0, 23)), [0.0, *[h for *_, h in BEFORE], 0, 0]
    )
    assert all(c.osm.startswith("FI:") for c in CATALOG)


def test_lookups_by_name_and_osm_value() -> None:
    assert CATALOG.by_name("give_way").code == 2
    assert CATALOG.by_osm("FI:231").name == "give_way"
    assert CATALOG.by_osm("FI:B5").name == "give_way"  # the 2020 numbering, an alias
    assert CATALOG.by_osm(" FI:361[40] ").name == "speed_limit_40"
    assert CATALOG.by_osm("FI:363[30]").name == "speed_limit_30"  # the zone sign
    assert CATALOG.code_of("stop") == CATALOG.code_of("FI:232") == CATALOG.code_of("FI:B6") == 1
    assert CATALOG.by_ref("FI:334") is CATALOG.by_code(18)
    assert CATALOG.code("no_parking") == 7
    with pytest.raises(UnknownSignClass):
        CATALOG.by_osm("stop")  # a name is no OSM value
    with pytest.raises(UnknownSignClass):
        CATALOG.by_name("FI:232")


@pytest.mark.parametrize(
    ("lookup", "ref", "named"),
    [
        ("by_osm", "DE:206", "OSM value 'DE:206'"),
        ("code_of", "stopp", "name or OSM value 'stopp'"),
        ("by_name", "stopp", "name 'stopp'"),
        ("by_code", 999, "code 999"),
    ],
)
def test_an_unknown_class_names_the_value_and_some_known_ones(lookup, ref, named) -> None:
    with pytest.raises(UnknownSignClass) as e:
        getattr(CATALOG, lookup)(ref)
    msg = str(e.value)
    assert msg.startswith(f"unknown sign class {named} (known: FI:232 (stop), FI:231 (give_way),")
    assert msg.endswith("... 20 classes)")
    assert isinstance(e.value, KeyError) and isinstance(e.value, ValueError)
    assert e.value.ref == ref


def test_size_overrides_take_names_or_osm_values() -> None:
    cat = CATALOG.with_sizes({"stop": 0.9, "FI:231": 0.7})
    assert cat.by_name("stop").height_m == 0.9 and cat.by_name("give_way").height_m == 0.7
    assert CATALOG.by_name("stop").height_m == 0.75  # immutable
    with pytest.raises(UnknownSignClass, match="'no_such_sign'"):
        CATALOG.with_sizes({"no_such_sign": 1.0})


def _c(code: int, name: str, osm: str = "", *aliases: str, h: float = 0.6, rel: float = 0.1):
    return SignClass(code, name, h, rel, osm, aliases)


@pytest.mark.parametrize(
    ("classes", "message"),
    [
        ([_c(1, "a"), _c(1, "b")], "sign class 1 ('b'): code: 1 is already 'a'"),
        ([_c(1, "a"), _c(2, "a")], "name: 'a' already names class 1"),
        ([_c(1, "a", "X:1"), _c(2, "b", "", "X:1")], "osm_aliases: 'X:1' already names class 1"),
        ([_c(1, "a"), _c(2, "b", "a")], "osm: 'a' already names class 1"),
        ([_c(1, "a", "X:1", "X:1")], "osm_aliases: 'X:1' is given twice"),
        ([_c(0, "a")], "code: 0 is not a wire code"),
        ([_c(65536, "a")], "code: 65536 is not a wire code"),
        ([_c(1, "a", h=0.0)], "height_m: must be > 0"),
        ([_c(1, "a", h=float("nan"))], "height_m: must be > 0"),
        ([_c(1, "a", rel=1.0)], "size_rel_sigma: must be in (0, 1)"),
        ([_c(1, "A b")], "name: 'A b' is not a snake_case name"),
        ([_c(1, "a", "X:1;X:2")], "osm: 'X:1;X:2': one traffic_sign value"),
    ],
)
def test_a_catalogue_keeps_its_invariants(classes, message) -> None:
    with pytest.raises(SignCatalogError) as e:
        SignCatalog(classes)
    assert message in str(e.value)


def test_a_class_may_have_its_name_as_osm_value() -> None:
    assert SignCatalog([SignClass(1, "stop", 0.7, osm="stop")]).code_of("stop") == 1


# --- the catalogue file ----------------------------------------------------------------------


def test_the_deploy_file_restates_the_defaults() -> None:
    path = ROOT / "deploy" / "signs.toml"
    assert list(SignCatalog.from_toml(path)) == list(CATALOG)
    assert list(SignCatalog.from_toml(path, base=SignCatalog([]))) == list(CATALOG)


def test_a_file_adds_a_class_and_overrides_a_size(tmp_path: Path) -> None:
    f = tmp_path / "signs.toml"
    f.write_text(
        DE_CLASS + '\n[[class]]\ncode = 4\nname = "speed_limit_30"\nheight_m = 0.9\n'
        'osm_aliases = ["FI:C32[30]"]\n'
    )
    cat = SignCatalog.from_toml(f)
    assert len(cat) == 21
    de = cat.by_osm("DE:306")
    assert (de.code, de.name, de.height_m, de.size_rel_sigma) == (
        1000,
        "de_priority_road",
        0.6,
        0.05,
    )
    assert cat.code_of("de_priority_road") == 1000 and 1000 in cat
    sl30 = cat.by_code(4)
    assert (sl30.height_m, sl30.osm, sl30.osm_aliases) == (0.9, "FI:361[30]", ("FI:C32[30]",))
    with pytest.raises(UnknownSignClass):
        cat.by_osm("FI:363[30]")  # the entry's aliases replace the old ones
    np.testing.assert_allclose(cat.heights(np.array([4, 5, 1000, 999])), [0.9, 0.64, 0.6, 0.0])
    assert [c for c in cat if c.code not in (4, 1000)] == [c for c in CATALOG if c.code != 4]
    assert CATALOG.by_code(4).height_m == 0.64 and 1000 not in CATALOG


def test_a_german_deployment_gives_its_values_to_the_default_codes() -> None:
    doc = {"class": [{"code": 1, "name": "stop", "osm": "DE:206", "osm_aliases": []}]}
    cat = SignCatalog.from_mapping(doc)
    assert cat.code_of("DE:206") == 1 and cat.by_code(1).height_m == 0.75
    with pytest.raises(UnknownSignClass):
        cat.by_osm("FI:232")


NEW = {"code": 1000, "name": "de_priority_road", "osm": "DE:306", "height_m": 0.6}


X = {"code": 1001, "name": "x", "osm": "X:1", "height_m": 0.6}
"""Another valid new class."""
SL30 = {"code": 4, "name": "speed_limit_30"}


@pytest.mark.parametrize(
    ("entry", "message"),
    [
        ({**NEW, "code": 0}, "code: 0 is not a wire code (1-65535)"),
        ({**NEW, "code": 65536}, "code: 65536 is not a wire code (1-65535)"),
        ({**NEW, "code": "1000"}, "code: expected an integer, got str"),
        ({**NEW, "code": True}, "code: expected an integer, got bool"),
        ({**NEW, "code": 1000.0}, "code: expected an integer, got float"),
        ({**NEW, "code": 1001}, "name: 'de_priority_road' already names class 1000"),
        ({**NEW, "code": 1001, "name": "x"}, "osm: 'DE:306' already names class 1000"),
        ({**X, "code": 1000}, "code: 1000 is given again (class[0])"),
        ({**X, "name": "stop"}, "name: 'stop' already names class 1 ('stop')"),
        ({**X, "osm": "FI:232"}, "osm: 'FI:232' already names class 1 ('stop')"),
        ({**X, "osm_aliases": ["FI:B6"]}, "osm_aliases: 'FI:B6' already names class 1"),
        ({**X, "osm_aliases": "X:2"}, "osm_aliases: expected a list"),
        ({**X, "osm_aliases": [2]}, "osm_aliases[0]: expected a string"),
        ({**X, "osm": ""}, "osm: expected a non-empty string"),
        ({**X, "name": "Not Snake"}, "name: 'Not Snake' is not a snake_case name"),
        ({"code": 1001, "name": "x", "height_m": 0.6}, "osm: missing (code 1001 is a new class)"),
        ({"code": 1001, "name": "x", "osm": "X:1"}, "height_m: missing (code 1001 is a new"),
        ({"name": "x"}, "code: missing"),
        ({"code": 1001}, "name: missing"),
        ({**X, "height_m": 0}, "height_m: must be > 0 and finite, got 0"),
        ({**X, "height_m": -0.6}, "height_m: must be > 0"),
        ({**X, "height_m": "0.6"}, "height_m: expected a number, got str"),
        ({**X, "size_rel_sigma": 0.0}, "size_rel_sigma: must be in (0, 1) and finite"),
        ({**X, "size_rel_sigma": -0.1}, "size_rel_sigma: must be in (0, 1)"),
        ({**SL30, "name": "speed_limit_40"}, "name: code 4 is 'speed_limit_30' in the base"),
        ({**SL30, "height_m": 0.0}, "height_m: must be > 0"),
        ({**SL30, "osm": "FI:232"}, "osm: 'FI:232' already names class 1"),
        ({**X, "colour": "blue"}, "colour: unknown key (known: code, name, osm"),
    ],
)
def test_each_bad_entry_is_named_with_its_field(entry, message: str) -> None:
    doc = {"format": 1, "class": [NEW, entry]}
    with pytest.raises(SignCatalogError) as e:
        SignCatalog.from_mapping(doc, source="deploy/x.toml")
    assert str(e.value).startswith(f"deploy/x.toml: class[1].{message}"), str(e.value)


def test_an_entry_that_is_no_table() -> None:
    with pytest.raises(SignCatalogError, match=r"^class\[0\]: expected a table"):
        SignCatalog.from_mapping({"class": ["stop"]})


@pytest.mark.parametrize(
    ("doc", "message"),
    [
        ({"classes": []}, "classes: unknown key (known: format, class)"),
        ({"format": 2}, "format: 2 is not a known format (1)"),
        ({"class": {"code": 1}}, "class: expected an array of tables"),
    ],
)
def test_bad_top_level_keys(doc, message: str) -> None:
    with pytest.raises(SignCatalogError, match=f"^{message.replace('(', '.').replace(')', '.')}"):
        SignCatalog.from_mapping(doc)


def test_unreadable_and_malformed_files(tmp_path: Path) -> None:
    with pytest.raises(SignCatalogError, match=r"missing\.toml: cannot read"):
        SignCatalog.from_toml(tmp_path / "missing.toml")
    f = tmp_path / "broken.toml"
    f.write_text("[[class]\ncode = 1")
    with pytest.raises(SignCatalogError, match=r"broken\.toml: not valid TOML"):
        SignCatalog.from_toml(f)
    f.write_text(DE_CLASS.replace("0.6", "-0.6"))
    with pytest.raises(SignCatalogError, match=r"broken\.toml: class\[0\]\.height_m: must be > 0"):
        SignCatalog.from_toml(f)
    assert issubclass(SignCatalogError, ValueError)


# --- ingest: the classes of its catalogue, each other code refused by name ---------------------


def _upload(classes: list[int], vehicle: str = "veh-1") -> bytes:
    obs = make_observations(len(classes), t=time.time())
    obs.sign_class[:] = classes
    return ObservationBatch(vehicle, 7, 1, time.time(), obs).to_bytes()


@pytest.fixture
def de_catalog(tmp_path: Path) -> Path:
    f = tmp_path / "signs.toml"
    f.write_text(DE_CLASS)
    return f


def test_decoder_accepts_an_added_class_only_with_the_catalogue(de_catalog: Path) -> None:
    data = _upload([1000, 4, 999])
    batch, rejected = ObservationBatch.from_bytes_partial(
        data, catalog=SignCatalog.from_toml(de_catalog)
    )
    assert batch.obs.sign_class.tolist() == [1000, 4]
    assert [(r.obs_id, r.field) for r in rejected] == [(3, "obs.sign_class")]
    assert rejected[0].reason.startswith("unknown sign class 999 ")
    batch, rejected = ObservationBatch.from_bytes_partial(data)  # the default catalogue
    assert batch.obs.sign_class.tolist() == [4]
    assert [(r.obs_id, r.field) for r in rejected] == [(1, "obs.sign_class"), (3, "obs.sign_class")]
    assert [r.reason.split(" (")[0] for r in rejected] == [
        "unknown sign class 1000",
        "unknown sign class 999",
    ]


def _stage(svc: IngestService, data: bytes, vehicle: str = "veh-1"):
    with svc.transaction([svc.writer]):
        ack, entries = svc._stage(Item("upload", keys.upload(vehicle), data))
    return ack, entries


def test_ingest_takes_the_classes_of_its_catalogue(tmp_path: Path, de_catalog: Path) -> None:
    svc = IngestService(
        ServiceOptions(data_dir=tmp_path / "var"), IngestConfig(catalog=str(de_catalog))
    )
    try:
        ack, entries = _stage(svc, _upload([1000, 1000, 999]))
        assert ack.error is None and ack.accepted.tolist() == [1, 2]
        assert [(r.obs_id, r.field) for r in ack.rejected] == [(3, "obs.sign_class")]
        assert "999" in ack.rejected[0].reason
        assert len(entries) >= 1 and svc.counters["accepted"] == 2
        assert svc.rejected["obs.sign_class"] == 1
    finally:
        svc.db.close()
    plain = IngestService(ServiceOptions(data_dir=tmp_path / "var2"))
    try:
        ack, _ = _stage(plain, _upload([1000]))
        assert [(r.obs_id, r.field) for r in ack.rejected] == [(1, "obs.sign_class")]
        assert ack.rejected[0].reason.startswith("unknown sign class 1000 ")
    finally:
        plain.db.close()


def test_ingest_refuses_a_bad_catalogue_before_touching_its_data_dir(tmp_path: Path) -> None:
    bad = tmp_path / "signs.toml"
    bad.write_text(DE_CLASS.replace("code = 1000", "code = 0"))
    with pytest.raises(ConfigError, match=r"^ingest\.catalog: .*signs\.toml: class\[0\]\.code: 0 "):
        IngestService(ServiceOptions(data_dir=tmp_path / "var"), IngestConfig(catalog=str(bad)))
    with pytest.raises(ConfigError, match=r"^ingest\.catalog: .*nope\.toml: cannot read"):
        IngestService(
            ServiceOptions(data_dir=tmp_path / "var"),
            IngestConfig(catalog=str(tmp_path / "nope.toml")),
        )
    assert not (tmp_path / "var").exists()
