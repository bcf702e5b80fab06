#!/usr/bin/env python3
"""Sanity tests for scripts/cgal_reference.py. Run: python3 scripts/test_cgal_reference.py"""
import json
import os
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import cgal_reference as C  # noqa: E402

# A CityGML 2.0 building. Large UTM-like coordinates test the local origin.
# Wall: 4 x 3 in the vertical plane y = 5403700, window hole 1.5 x 1.2 -> 10.2 m2, 8 triangles
# (BUILD.md section 3). srsDimension sits on the MultiSurface (an ancestor), one vertex per line.
CITYGML2 = """<?xml version="1.0" encoding="UTF-8"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0"
  xmlns:bldg="http://www.opengis.net/citygml/building/2.0"
  xmlns:gml="http://www.opengis.net/gml" xmlns:xlink="http://www.w3.org/1999/xlink">
 <core:cityObjectMember><bldg:Building gml:id="B1">
  <bldg:boundedBy><bldg:WallSurface>
   <bldg:lod3MultiSurface><gml:MultiSurface srsDimension="3">
    <gml:surfaceMember><gml:Polygon gml:id="wall">
     <gml:exterior><gml:LinearRing><gml:posList>
678000 5403700 400
678004 5403700 400
678004 5403700 403
678000 5403700 403
678000 5403700 400
     </gml:posList></gml:LinearRing></gml:exterior>
     <gml:interior><gml:LinearRing><gml:posList>
678001 5403700 401
678001 5403700 402.2
678002.5 5403700 402.2
678002.5 5403700 401
678001 5403700 401
     </gml:posList></gml:LinearRing></gml:interior>
    </gml:Polygon></gml:surfaceMember>
    <gml:surfaceMember xlink:href="#wall"/>
    <gml:surfaceMember><gml:Polygon gml:id="zero">
     <gml:exterior><gml:LinearRing><gml:posList>
0 0 0 1 1 1 2 2 2 0 0 0</gml:posList></gml:LinearRing></gml:exterior>
    </gml:Polygon></gml:surfaceMember>
    <gml:surfaceMember><gml:Polygon>
     <gml:exterior><gml:LinearRing>
      <gml:pos>10 0 0</gml:pos><gml:pos>12 0 0</gml:pos><gml:pos>12 0 0</gml:pos>
      <gml:pos>12 2 0</gml:pos><gml:pos>10 2 0</gml:pos><gml:pos>10 2 0</gml:pos>
      <gml:pos>10 0 0</gml:pos>
     </gml:LinearRing></gml:exterior>
    </gml:Polygon></gml:surfaceMember>
   </gml:MultiSurface></bldg:lod3MultiSurface>
  </bldg:WallSurface></bldg:boundedBy>
  <bldg:outerBuildingInstallation><bldg:BuildingInstallation><bldg:lod3Geometry>
   <gml:MultiGeometry><gml:geometryMember><gml:LineString><gml:posList srsDimension="3">
0 0 0 1 0 0</gml:posList></gml:LineString></gml:geometryMember>
   <gml:geometryMember><gml:Polygon gml:id="bowtie"><gml:exterior><gml:LinearRing>
    <gml:posList srsDimension="2">0 0 2 2 2 0 0 1 0 0</gml:posList>
   </gml:LinearRing></gml:exterior></gml:Polygon></gml:geometryMember>
   <gml:geometryMember><gml:Polygon gml:id="badhole"><gml:exterior><gml:LinearRing>
    <gml:posList>0 0 5 4 0 5 4 4 5 0 4 5 0 0 5</gml:posList></gml:LinearRing></gml:exterior>
    <gml:interior><gml:LinearRing>
    <gml:posList>1 1 5 2 2 5 2 2 5 1 1 5</gml:posList></gml:LinearRing></gml:interior>
   </gml:Polygon></gml:geometryMember>
   </gml:MultiGeometry>
  </bldg:lod3Geometry></bldg:BuildingInstallation></bldg:outerBuildingInstallation>
 </bldg:Building></core:cityObjectMember>
</core:CityModel>
"""

# GML 3.2 (CityGML 3.0 style) with Triangle, Rectangle and gml:coordinates.
GML32 = """<?xml version="1.0" encoding="UTF-8"?>
<CityModel xmlns="http://www.opengis.net/citygml/3.0" xmlns:gml="http://www.opengis.net/gml/3.2">
 <gml:TriangulatedSurface><gml:patches>
  <gml:Triangle><gml:exterior><gml:LinearRing>
   <gml:pos srsDimension="3">0 0 0</gml:pos><gml:pos srsDimension="3">3 0 0</gml:pos>
   <gml:pos srsDimension="3">0 0 4</gml:pos><gml:pos srsDimension="3">0 0 0</gml:pos>
  </gml:LinearRing></gml:exterior></gml:Triangle>
 </gml:patches></gml:TriangulatedSurface>
 <gml:Surface><gml:patches>
  <gml:Rectangle><gml:exterior><gml:LinearRing>
   <gml:coordinates>0,0,1 0,5,1 2,5,1 2,0,1 0,0,1</gml:coordinates>
  </gml:LinearRing></gml:exterior></gml:Rectangle>
  <gml:PolygonPatch><gml:exterior><gml:LinearRing>
   <gml:posList>0 0 0 1 0 0 1 1 0 0.5 0.2 0 0 1 0 0 0 0</gml:posList>
  </gml:LinearRing></gml:exterior></gml:PolygonPatch>
 </gml:patches></gml:Surface>
</CityModel>
"""


def close(a, b, tol=1e-9):
    return abs(a - b) <= tol * max(1.0, abs(a), abs(b))


def run(text, name, tmp):
    path = os.path.join(tmp, name + ".gml")
    with open(path, "w") as f:
        f.write(text)
    out = os.path.join(tmp, "out")
    assert C.main(["--out", out, "--runs", "1", path]) == 0
    with open(os.path.join(out, name + ".json")) as f:
        return json.load(f)


def test_citygml2(tmp):
    d = run(CITYGML2, "wall", tmp)
    assert d["generator"] == "scripts/cgal_reference.py"
    assert d["cgal"] == C.CGAL_VERSION
    assert len(d["sha256"]) == 64
    # 5 polygons: wall, zero, dup, bowtie, badhole; the xlink and the LineString are not patches
    assert d["patches"] == 5, d["patches"]
    assert d["holes"] == 2, d["holes"]
    p = d["polygons"]
    assert [q["ordinal"] for q in p] == [0, 1, 2, 3, 4]
    assert [q["id"] for q in p] == ["wall", "zero", None, "bowtie", "badhole"]

    wall = p[0]
    assert wall["status"] == "ok" and wall["reason"] is None, wall
    assert wall["rings"] == 2 and wall["points"] == 8, wall
    assert wall["triangles"] == 8, wall
    assert close(wall["area"], 10.2), wall
    assert close(wall["area_projected"], 10.2), wall
    assert wall["planarity"] < 1e-9, wall

    zero = p[1]
    assert zero["status"] == "skipped" and zero["reason"] == "degenerate: zero area", zero
    assert zero["triangles"] == 0 and zero["points"] == 3, zero

    dup = p[2]  # 2 x 2 square with two doubled vertices: 6 points, 4 distinct
    assert dup["status"] == "ok", dup
    assert dup["points"] == 6 and dup["rings"] == 1, dup
    assert dup["triangles"] == 2, dup
    assert close(dup["area"], 4.0) and close(dup["area_projected"], 4.0), dup
    assert dup["planarity"] == 0.0, dup

    bowtie = p[3]  # srsDimension=2 posList, self-intersecting: CGAL adds a vertex
    assert bowtie["status"] == "skipped", bowtie
    assert bowtie["reason"].startswith("intersecting constraints"), bowtie

    badhole = p[4]  # hole with only 2 distinct points
    assert badhole["status"] == "skipped", badhole
    assert badhole["reason"] == "degenerate: fewer than 3 distinct points", badhole
    assert badhole["rings"] == 2, badhole


def test_gml32(tmp):
    d = run(GML32, "gml32", tmp)
    assert d["patches"] == 3 and d["holes"] == 0, d
    tri, rect, patch = d["polygons"]
    assert tri["type"] == "Triangle" and tri["triangles"] == 1 and close(tri["area"], 6.0), tri
    assert rect["type"] == "Rectangle" and rect["triangles"] == 2 and close(rect["area"], 10.0), rect
    # concave pentagon (notch at (0.5, 0.2)): 3 triangles, area 1 - 0.5*1*0.8
    assert patch["type"] == "PolygonPatch" and patch["triangles"] == 3, patch
    assert close(patch["area"], 0.6) and close(patch["area_projected"], 0.6), patch


def test_helpers():
    assert C.round_sig(1.23456789012345678) == 1.23456789012
    assert C.round_sig(0.0) == 0.0 and C.round_sig(None) is None
    # even-odd over two rings: a point in the hole is outside
    sq = [(0, 0), (4, 0), (4, 4), (0, 4)]
    hole = [(1, 1), (1, 2), (2, 2), (2, 1)]
    edges = []
    for r in (sq, hole):
        edges += [(r[i][0], r[i][1], r[(i + 1) % 4][0], r[(i + 1) % 4][1]) for i in range(4)]
    assert C.inside_even_odd(3, 3, edges)
    assert not C.inside_even_odd(1.5, 1.5, edges)
    assert not C.inside_even_odd(5, 1, edges)


if __name__ == "__main__":
    with tempfile.TemporaryDirectory() as tmp:
        test_helpers()
        test_citygml2(tmp)
        test_gml32(tmp)
    print("test_cgal_reference.py: all tests passed")
