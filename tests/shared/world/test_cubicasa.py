"""CubiCasa5K SVG parsing: the kit sample, a synthetic plan with exact coordinates, transforms and bad input."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from swarmmap.shared.world.cubicasa import MAX_BYTES, load_cubicasa, parse_cubicasa
from swarmmap.shared.world.floorplan import PlanError
from tests.conftest import KIT_DATA

SAMPLE = KIT_DATA / "cubicasa5k" / "353" / "model.svg"
SVG_NS = "http://www.w3.org/2000/svg"


@pytest.fixture(scope="module")
def sample():
    if not SAMPLE.exists():
        pytest.skip("kit data ../shared/data/cubicasa5k not present")
    return SAMPLE.read_text(encoding="utf-8"), load_cubicasa(SAMPLE)


def test_sample_counts_match_an_independent_count(sample):
    text, plan = sample
    root = ET.fromstring(text)
    groups = list(root.iter(f"{{{SVG_NS}}}g"))

    def by_id(name: str) -> int:
        return sum(g.get("id") == name for g in groups)

    rooms = sum((g.get("class") or "").split()[:1] == ["Space"] for g in groups)
    counted = (by_id("Wall"), by_id("Railing"), by_id("Door"), by_id("Window"), rooms)
    assert counted == (len(re.findall(r'\bid="Wall"', text)), 4, 12, 6, len(re.findall(r'class="Space ', text)))
    parsed = (len(plan.walls), len(plan.railings), len(plan.doors), len(plan.windows), len(plan.rooms))
    assert parsed == counted == (26, 4, 12, 6, 17)


def test_sample_extent_types_and_coordinates(sample):
    _, plan = sample
    # Walls span 10.01 x 11.97 m; the railings and the terrace north of the flat stretch y to 14.04 m.
    assert plan.width_m == pytest.approx(10.007, abs=0.05)
    assert plan.height_m == pytest.approx(14.041, abs=0.05)
    walls = np.concatenate(plan.walls)
    assert np.ptp(walls, axis=0) == pytest.approx([10.007, 11.970], abs=0.05)
    assert all(isinstance(kind, str) and kind for kind, _ in plan.rooms)
    assert sorted({kind for kind, _ in plan.rooms}) == [
        "Bath", "Bedroom", "Closet", "Den", "Dining", "DraughtLobby", "Entry", "Kitchen", "LivingRoom", "Outdoor", "Storage",
        "Undefined", "Utility",
    ]  # fmt: skip
    everything = plan.walls + plan.railings + plan.doors + plan.windows + [poly for _, poly in plan.rooms]
    for poly in everything:
        assert poly.dtype == np.float64 and poly.ndim == 2 and poly.shape[1] == 2 and len(poly) >= 3
        assert np.isfinite(poly).all() and (poly >= 0).all()


def test_sample_door_is_its_own_outline_flipped(sample):
    _, plan = sample
    height = 1486.4200744628906  # the sample's viewBox height
    first_door = [(430.10, 289.81), (509.79, 289.77), (509.81, 320.08), (430.12, 320.12)]
    expected = [(x * 0.01, (height - y) * 0.01) for x, y in first_door]
    np.testing.assert_allclose(plan.doors[0], expected, atol=1e-9)


SYNTHETIC = f"""<?xml version="1.0"?>
<svg xmlns="{SVG_NS}" width="500" height="400" viewBox="0 0 500 400">
 <g id="Model" class="Model">
  <g class="Space Kitchen"><polygon points="100,100 300,100 300,300 100,300 "/></g>
  <g id="Wall" class="Wall External">
   <polygon points="90,90 310,90 310,100 90,100"/>
   <g id="Door" class="Door Swing">
    <g class="Panel"><polygon points="0,0 1,0 1,1"/></g>
    <polygon points="150,90 200,90 200,100 150,100"/>
   </g>
  </g>
  <g id="Wall" class="Wall"><polygon points="90,300,310,300,310,310,90,310"/></g>
  <g id="Wall" class="Wall"><polygon points=" 90,100  100,100
      100,300 90,300 "/></g>
  <g id="Wall" class="Wall" transform="matrix(1,0,0,1,100,50)">
   <polygon points="200,50 210,50 210,250 200,250"/>
   <g id="Window" class="Window Regular"><polygon points="200,100 210,100 210,150 200,150"/></g>
  </g>
  <g id="Railing" class="Railing"><polygon points="310,150 320,150 320,160 310,160"/></g>
 </g>
</svg>
"""


def metres(points: list[tuple[float, float]], height: float = 400.0) -> np.ndarray:
    return np.array([(x / 100, (height - y) / 100) for x, y in points])


def test_synthetic_plan_exact_coordinates():
    plan = parse_cubicasa(SYNTHETIC)
    assert len(plan.walls) == 4 and len(plan.doors) == 1 and len(plan.windows) == 1 and len(plan.railings) == 1
    np.testing.assert_allclose(plan.walls[0], [(0.9, 3.1), (3.1, 3.1), (3.1, 3.0), (0.9, 3.0)], atol=1e-12)
    np.testing.assert_allclose(plan.walls[1], metres([(90, 300), (310, 300), (310, 310), (90, 310)]), atol=1e-12)
    np.testing.assert_allclose(plan.walls[2], metres([(90, 100), (100, 100), (100, 300), (90, 300)]), atol=1e-12)
    # matrix(1,0,0,1,100,50) moves the right wall and the window nested in it by (+100, +50) SVG units.
    np.testing.assert_allclose(plan.walls[3], [(3.0, 3.0), (3.1, 3.0), (3.1, 1.0), (3.0, 1.0)], atol=1e-12)
    np.testing.assert_allclose(plan.windows[0], metres([(300, 150), (310, 150), (310, 200), (300, 200)]), atol=1e-12)
    # The door's own polygon, not the panel polygon nested before it.
    np.testing.assert_allclose(plan.doors[0], [(1.5, 3.1), (2.0, 3.1), (2.0, 3.0), (1.5, 3.0)], atol=1e-12)
    np.testing.assert_allclose(plan.railings[0], metres([(310, 150), (320, 150), (320, 160), (310, 160)]), atol=1e-12)
    assert [kind for kind, _ in plan.rooms] == ["Kitchen"]
    np.testing.assert_allclose(plan.rooms[0][1], [(1, 3), (3, 3), (3, 1), (1, 1)], atol=1e-12)
    assert plan.width_m == pytest.approx(2.3) and plan.height_m == pytest.approx(2.2)


def test_height_falls_back_to_attribute_then_to_max_y_and_scale_applies():
    no_box = SYNTHETIC.replace(' viewBox="0 0 500 400"', "").replace('height="400"', 'height="400px"')
    np.testing.assert_allclose(parse_cubicasa(no_box).walls[0], parse_cubicasa(SYNTHETIC).walls[0])
    bare = SYNTHETIC.replace(' viewBox="0 0 500 400"', "").replace(' height="400"', "").encode()
    plan = parse_cubicasa(bare, scale_m_per_unit=0.02)  # the lowest point (y = 310) lands on y = 0
    np.testing.assert_allclose(plan.walls[0], [(1.8, 4.4), (6.2, 4.4), (6.2, 4.2), (1.8, 4.2)], atol=1e-12)
    assert plan.width_m == pytest.approx(4.6)


@pytest.mark.parametrize(
    "outer, inner, expected",
    [
        ("translate(10,20)", "rotate(90)", (10, 40)),  # (10,0) -scale(2)-> (20,0) -rotate-> (0,20) -translate-> (10,40)
        ("translate(10)", "scale(3 1)", (70, 0)),
        ("", "rotate(90, 10, 0)", (10, 10)),
        ("matrix(0 1 -1 0 0 0)", "translate(0,5) skewX(45)", (-5, 20)),
        ("scale(0.5)", "skewY(45)", (10, 10)),
    ],
)
def test_ancestor_transforms_compose(outer, inner, expected):
    svg = (
        f'<svg xmlns="{SVG_NS}" viewBox="0 0 100 100"><g transform="{outer}"><g id="Wall" transform="{inner}">'
        '<polygon transform="scale(2)" points="0,0 10,0 10,5"/></g></g></svg>'
    )
    wall = parse_cubicasa(svg, scale_m_per_unit=1.0).walls[0]
    assert (wall[1, 0], 100 - wall[1, 1]) == pytest.approx(expected)


def test_non_namespaced_svg_parses():
    plan = parse_cubicasa(SYNTHETIC.replace(f' xmlns="{SVG_NS}"', ""))
    assert len(plan.walls) == 4 and len(plan.rooms) == 1


def wall_svg(points: str, transform: str = "") -> str:
    attr = f' transform="{transform}"' if transform else ""
    return (
        f'<svg xmlns="{SVG_NS}" viewBox="0 0 10 10"><g id="Wall"><polygon points="0,0 1,0 1,1"/></g>'
        f'<g id="Wall"{attr}><polygon points="{points}"/></g></svg>'
    )


BILLION_LAUGHS = '<?xml version="1.0"?><!DOCTYPE svg [<!ENTITY a "aaaa"><!ENTITY b "&a;&a;&a;&a;">]><svg>&b;</svg>'


@pytest.mark.parametrize(
    "content, problem",
    [
        ("this is not xml", "not a valid SVG/XML"),
        (SYNTHETIC[: len(SYNTHETIC) // 2], "not a valid SVG/XML"),
        ("", "not a valid SVG/XML"),
        ("<html><g id='Wall'/></html>", "not an SVG file (root element is <html>)"),
        (f'<svg xmlns="{SVG_NS}"><g id="Floor"><polygon points="0,0 1,0 1,1"/></g></svg>', 'no <g id="Wall"> found'),
        (wall_svg("0,0 5,5"), "wall polygon #2 has only 2 points"),
        (wall_svg(""), "wall polygon #2 has only 0 points"),
        (wall_svg("0,0 5,5 5"), "wall polygon #2 has an odd number of coordinates (5)"),
        (wall_svg("0,0 5,abc 5,0"), "wall polygon #2 has a non-numeric value 'abc'"),
        (wall_svg("0,0 5,nan 5,0"), "wall polygon #2 has a non-numeric value 'nan'"),
        (wall_svg("0,0 5,1e999 5,0"), "wall polygon #2 has a non-finite value '1e999'"),
        (wall_svg("0,0 5,5 5,0", "skew(3)"), "cannot parse transform 'skew(3)' on <g id=\"Wall\">"),
        (wall_svg("0,0 5,5 5,0", "matrix(1,0,0)"), "matrix() takes 6 numbers"),
        (wall_svg("0,0 5,5 5,0", "translate(1,2"), "cannot parse transform 'translate(1,2'"),
        (wall_svg("0,0 5,5 5,0", "scale(x)"), "has a non-numeric value 'x'"),
        (wall_svg("0,0 5,5 5,0", "scale(1e300) scale(1e300)"), "non-finite coordinates after its transforms"),
        (f'<svg xmlns="{SVG_NS}"><g id="Wall"><g/></g></svg>', "wall polygon #1 is missing"),
        (
            f'<svg xmlns="{SVG_NS}" viewBox="0 0 a 1"><g id="Wall"><polygon points="0,0 1,0 1,1"/></g></svg>',
            "the viewBox has a non-numeric value 'a'",
        ),
        (BILLION_LAUGHS, "DOCTYPE/ENTITY, refused"),
        ('<!DOCTYPE svg SYSTEM "http://example.com/x.dtd"><svg/>', "DOCTYPE/ENTITY, refused"),
        ("<g>" * 300 + '<g id="Wall"/>' + "</g>" * 300, "not an SVG file"),
        (f'<svg xmlns="{SVG_NS}">' + "<g>" * 300 + "</g>" * 300 + "</svg>", "nested more than 256 levels deep"),
    ],
)
def test_bad_files_raise_plan_error_naming_file_and_problem(tmp_path, content, problem):
    path = tmp_path / "bad_plan.svg"
    path.write_text(content, encoding="utf-8")
    with pytest.raises(PlanError) as err:
        load_cubicasa(path)
    assert str(path) in str(err.value) and problem in str(err.value)
    assert err.value.path == str(path)


def test_doctype_hidden_by_another_encoding_is_refused(tmp_path):
    path = tmp_path / "utf16.svg"
    path.write_bytes(BILLION_LAUGHS.replace('"1.0"?>', '"1.0" encoding="UTF-16"?>', 1).encode("utf-16"))
    with pytest.raises(PlanError, match="utf16.svg: .*DOCTYPE/ENTITY, refused"):
        load_cubicasa(path)


def test_missing_unreadable_and_oversized_files(tmp_path):
    with pytest.raises(PlanError, match=r"nope\.svg: file does not exist"):
        load_cubicasa(tmp_path / "nope.svg")
    (tmp_path / "folder.svg").mkdir()  # exists but cannot be read as a file (chmod does not stop root)
    with pytest.raises(PlanError, match=r"folder\.svg: cannot read file: Is a directory"):
        load_cubicasa(tmp_path / "folder.svg")
    huge = tmp_path / "huge.svg"
    with huge.open("wb") as f:
        f.truncate(MAX_BYTES + 1)  # sparse: no 50 MB written
    with pytest.raises(PlanError, match=r"huge\.svg: file is 52428801 bytes, over the 50 MB limit"):
        load_cubicasa(huge)
    with pytest.raises(PlanError, match="big: document is over the 50 MB limit"):
        parse_cubicasa(b" " * (MAX_BYTES + 1), source="big")


def test_parse_names_its_source_and_rejects_a_bad_scale():
    with pytest.raises(PlanError, match="^upload.svg: not an SVG file"):
        parse_cubicasa("<html/>", source="upload.svg")
    with pytest.raises(ValueError, match="scale_m_per_unit"):
        parse_cubicasa(SYNTHETIC, scale_m_per_unit=0)
