#!/usr/bin/env python3
"""Writes the seed inputs of every fuzz target into fuzz/seeds/<target>/ (small, valid
files of each format; libFuzzer mutates from them). Run from the repository root:
`python3 fuzz/make_seeds.py`. Deterministic: the same files every time."""
import json
import os
import struct

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "seeds")


def put(target, name, data):
    d = os.path.join(ROOT, target)
    os.makedirs(d, exist_ok=True)
    if isinstance(data, str):
        data = data.encode("utf-8")
    with open(os.path.join(d, name), "wb") as f:
        f.write(data)


# ------------------------------------------------------------------ CityGML
NS2 = ('xmlns:core="http://www.opengis.net/citygml/2.0" '
       'xmlns:bldg="http://www.opengis.net/citygml/building/2.0" '
       'xmlns:gen="http://www.opengis.net/citygml/generics/2.0" '
       'xmlns:app="http://www.opengis.net/citygml/appearance/2.0" '
       'xmlns:gml="http://www.opengis.net/gml" xmlns:xlink="http://www.w3.org/1999/xlink"')


def ring(pts):
    return " ".join(f"{x} {y} {z}" for x, y, z in pts + [pts[0]])


WALL = [(0, 0, 0), (10, 0, 0), (10, 0, 6), (0, 0, 6)]
HOLE = [(2, 0, 1), (2, 0, 2), (4, 0, 2), (4, 0, 1)]
ROOF = [(0, 0, 6), (10, 0, 6), (10, 8, 6), (0, 8, 6)]
CITYGML2 = f'''<?xml version="1.0" encoding="UTF-8"?>
<core:CityModel {NS2}>
<gml:boundedBy><gml:Envelope srsName="EPSG:25832" srsDimension="3"><gml:lowerCorner>0 0 0</gml:lowerCorner><gml:upperCorner>10 8 6</gml:upperCorner></gml:Envelope></gml:boundedBy>
<core:cityObjectMember><bldg:Building gml:id="B1">
<gml:name>House &amp; garden</gml:name>
<gen:stringAttribute name="note"><gen:value>x</gen:value></gen:stringAttribute>
<gen:doubleAttribute name="h"><gen:value>6.5</gen:value></gen:doubleAttribute>
<bldg:measuredHeight uom="m">6.0</bldg:measuredHeight>
<bldg:lod3Solid><gml:Solid><gml:exterior><gml:CompositeSurface>
<gml:surfaceMember xlink:href="#P1"/><gml:surfaceMember xlink:href="#P2"/>
</gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod3Solid>
<bldg:boundedBy><bldg:WallSurface gml:id="W1"><bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember>
<gml:Polygon gml:id="P1"><gml:exterior><gml:LinearRing gml:id="R1"><gml:posList srsDimension="3">{ring(WALL)}</gml:posList></gml:LinearRing></gml:exterior>
<gml:interior><gml:LinearRing><gml:posList>{ring(HOLE)}</gml:posList></gml:LinearRing></gml:interior></gml:Polygon>
</gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface>
<bldg:opening><bldg:Window gml:id="O1"><bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:Polygon><gml:exterior><gml:LinearRing>
<gml:pos>2 0 1</gml:pos><gml:pos>4 0 1</gml:pos><gml:pos>4 0 2</gml:pos><gml:pos>2 0 2</gml:pos><gml:pos>2 0 1</gml:pos>
</gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface></bldg:Window></bldg:opening>
</bldg:WallSurface></bldg:boundedBy>
<bldg:boundedBy><bldg:RoofSurface><bldg:lod2MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:OrientableSurface orientation="-"><gml:baseSurface>
<gml:Polygon gml:id="P2"><gml:exterior><gml:LinearRing><gml:coordinates cs="," ts=" ">0,0,6 10,0,6 10,8,6 0,8,6 0,0,6</gml:coordinates></gml:LinearRing></gml:exterior></gml:Polygon>
</gml:baseSurface></gml:OrientableSurface></gml:surfaceMember></gml:MultiSurface></bldg:lod2MultiSurface></bldg:RoofSurface></bldg:boundedBy>
</bldg:Building></core:cityObjectMember>
<app:appearanceMember><app:Appearance><app:theme>t</app:theme><app:surfaceDataMember><app:ParameterizedTexture>
<app:imageURI>a.png</app:imageURI><app:target uri="#P1"><app:TexCoordList><app:textureCoordinates ring="#R1">0 0 1 0 1 1 0 1 0 0</app:textureCoordinates></app:TexCoordList></app:target>
</app:ParameterizedTexture></app:surfaceDataMember><app:surfaceDataMember><app:X3DMaterial><app:diffuseColor>0.5 0.5 0.5</app:diffuseColor><app:transparency>0.1</app:transparency><app:target>#P2</app:target></app:X3DMaterial></app:surfaceDataMember></app:Appearance></app:appearanceMember>
</core:CityModel>
'''
put("citygml", "v2_building.gml", CITYGML2)
put("citygml", "v1_building.gml", CITYGML2.replace("citygml/2.0", "citygml/1.0").replace("building/2.0", "building/1.0")
    .replace("generics/2.0", "generics/1.0").replace("appearance/2.0", "appearance/1.0"))
NS3 = ('xmlns:core="http://www.opengis.net/citygml/3.0" '
       'xmlns:bldg="http://www.opengis.net/citygml/building/3.0" '
       'xmlns:con="http://www.opengis.net/citygml/construction/3.0" '
       'xmlns:gml="http://www.opengis.net/gml/3.2"')
CITYGML3 = f'''<?xml version="1.0" encoding="UTF-8"?>
<core:CityModel {NS3}><core:cityObjectMember><bldg:Building gml:id="B3">
<core:boundary><con:WallSurface gml:id="W3"><core:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember>
<gml:Polygon gml:id="P3"><gml:exterior><gml:LinearRing><gml:posList srsDimension="3">{ring(WALL)}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon>
</gml:surfaceMember></gml:MultiSurface></core:lod3MultiSurface>
<con:fillingSurface><con:WindowSurface gml:id="WS3"><core:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember>
<gml:Polygon><gml:exterior><gml:LinearRing><gml:posList>{ring(HOLE)}</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon>
</gml:surfaceMember></gml:MultiSurface></core:lod3MultiSurface></con:WindowSurface></con:fillingSurface>
</con:WallSurface></core:boundary></bldg:Building></core:cityObjectMember></core:CityModel>
'''
put("citygml", "v3_building.gml", CITYGML3)
put("citygml", "latin1.gml", CITYGML2.replace('encoding="UTF-8"', 'encoding="ISO-8859-1"')
    .replace("House &amp; garden", "H\u00e4user").encode("latin-1"))

# The citymodel target triangulates what the citygml target reads: the same seeds.
for name in ("v2_building.gml", "v1_building.gml", "v3_building.gml", "latin1.gml"):
    put("citymodel", name, open(os.path.join(ROOT, "citygml", name), "rb").read())

# ------------------------------------------------------------------ selection expressions
put("where", "class_and_attr.txt", "class=Window and measuredHeight >= 1200 cm")
put("where", "nested.txt", "not (level=part or within(\"DEBY 1\")) and text('a car') or label=3")
put("where", "dates_ids.txt", "creationDate>=2020-09-01 and id=B1 or category=tree")

# ------------------------------------------------------------------ PLY
CORE = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
        "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def splat_ply(fmt, n, rest=0, extra=True):
    props = CORE[:6] + [f"f_rest_{i}" for i in range(rest)] + CORE[6:]
    head = f"ply\nformat {fmt} 1.0\nelement vertex {n}\n"
    head += "".join(f"property float {p}\n" for p in props)
    if extra:
        head += "property int semantic_id\nproperty uchar label\n"
    head += "end_header\n"
    body = b""
    for v in range(n):
        vals = [v * 0.5, 1.0, -2.0, 0.1, 0.2, 0.3] + [0.01 * i for i in range(rest)] + [0.5, -3.0, -3.0, -3.0, 1.0, 0.0, 0.0, 0.0]
        if fmt == "ascii":
            body += (" ".join(repr(x) for x in vals) + (f" {-v} {v}" if extra else "") + "\n").encode()
        else:
            e = "<" if fmt == "binary_little_endian" else ">"
            body += struct.pack(f"{e}{len(vals)}f", *vals)
            if extra:
                body += struct.pack(f"{e}iB", -v, v)
    return head.encode() + body


put("ply_splat", "ascii_deg0.ply", splat_ply("ascii", 3))
put("ply_splat", "le_deg1.ply", splat_ply("binary_little_endian", 2, rest=9))
put("ply_splat", "be_deg0.ply", splat_ply("binary_big_endian", 2))
put("ply_splat", "le_floats.ply", splat_ply("binary_little_endian", 3, extra=False))


def mesh_ply(fmt):
    verts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 1)]
    faces = [((0, 1, 2), (0, 1, -1)), ((0, 2, 3), (0, 1, 2))]
    head = (f"ply\nformat {fmt} 1.0\ncomment gs4city citymodel mesh\nelement vertex {len(verts)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
            "property int feature_id\nproperty int surface_id\nproperty int part_id\nend_header\n")
    if fmt == "ascii":
        body = "".join(f"{x} {y} {z}\n" for x, y, z in verts)
        body += "".join(f"3 {a} {b} {c} {f} {s} {p}\n" for (a, b, c), (f, s, p) in faces)
        return (head + body).encode()
    e = "<" if fmt == "binary_little_endian" else ">"
    body = b"".join(struct.pack(f"{e}3f", *v) for v in verts)
    body += b"".join(struct.pack(f"{e}B3i3i", 3, *idx, *lab) for idx, lab in faces)
    return head.encode() + body


put("ply_mesh", "le.ply", mesh_ply("binary_little_endian"))
put("ply_mesh", "be.ply", mesh_ply("binary_big_endian"))
put("ply_mesh", "ascii.ply", mesh_ply("ascii"))

# ------------------------------------------------------------------ COLMAP
def split2(a, b):
    return struct.pack("<H", len(a)) + a + b


cams_bin = struct.pack("<Q", 2)
cams_bin += struct.pack("<IiQQ", 1, 1, 64, 48) + struct.pack("<4d", 50, 52, 32, 24)
cams_bin += struct.pack("<IiQQ", 2, 4, 64, 48) + struct.pack("<8d", 50, 52, 32, 24, -0.1, 0.01, 0.001, 0.0)
imgs_bin = struct.pack("<Q", 2)
imgs_bin += struct.pack("<I4d3dI", 1, 1, 0, 0, 0, 0.5, 0, 2, 1) + b"a.png\0" + struct.pack("<Q", 1) + struct.pack("<ddQ", 3.0, 4.0, 7)
imgs_bin += struct.pack("<I4d3dI", 2, 0.7071, 0.7071, 0, 0, 0, 0, 1, 2) + b"dir/b.jpg\0" + struct.pack("<Q", 0)
put("colmap_bin", "model.bin", split2(cams_bin, imgs_bin))
pts_bin = struct.pack("<Q", 1) + struct.pack("<Q3d3Bd", 7, 1, 2, 3, 255, 0, 10, 0.5) + struct.pack("<Q", 1) + struct.pack("<II", 1, 0)
put("colmap_bin", "points.bin", pts_bin)
cams_txt = "# Camera list\n1 PINHOLE 64 48 50 52 32 24\n2 SIMPLE_RADIAL 64 48 50 32 24 -0.05\n3 FULL_OPENCV 64 48 50 52 32 24 0.1 0.01 0 0 0 0 0 0\n"
imgs_txt = "# Image list\n1 1 0 0 0 0.5 0 2 1 a.png\n3 4 7\n2 0.7071 0.7071 0 0 0 0 1 2 b c.jpg\n\n"
put("colmap_txt", "model.txt", split2(cams_txt.encode(), imgs_txt.encode()))
put("colmap_txt", "points.txt", "# points\n7 1 2 3 255 0 10 0.5 1 0 2 1\n")

# ------------------------------------------------------------------ SAM
def rle_string(counts):
    """pycocotools' rleToString."""
    out = []
    for i, c in enumerate(counts):
        x = c - (counts[i - 2] if i > 2 else 0)
        while True:
            g = x & 0x1F
            x >>= 5
            more = (x != -1) if g & 0x10 else (x != 0)
            out.append(chr(48 + (g | 0x20 if more else g)))
            if not more:
                break
    return "".join(out)


masks = [
    {"segmentation": {"size": [4, 5], "counts": rle_string([5, 3, 12])}, "area": 3, "bbox": [1, 1, 0, 2],
     "predicted_iou": 0.9, "stability_score": 0.95, "point_coords": [[1.0, 2.0]], "crop_box": [0, 0, 5, 4]},
    {"segmentation": {"size": [4, 5], "counts": [3, 2, 15]}, "area": 2, "bbox": [0, 3, 0, 1],
     "predicted_iou": 0.8, "stability_score": 0.9},
]
put("sam", "masks.json", json.dumps(masks))
put("sam", "prompts.json", json.dumps({"dim": 3, "simulated": True, "prompts": {"window": [0.1, 0.2, 0.3], "door": [1, 0, 0]}}))
put("sam", "counts.txt", "0123456789:;<=>?@ABCDEFGHIJKLMNOPQRSTUVWXYZ[\\]^_`abcdefghijklmno")

# ------------------------------------------------------------------ npy
def npy(descr, shape, payload, version=1):
    shape_txt = f"({shape[0]},)" if len(shape) == 1 else "(" + ", ".join(map(str, shape)) + ")"
    h = "{'descr': '%s', 'fortran_order': False, 'shape': %s, }" % (descr, shape_txt)
    pre = 10 if version == 1 else 12
    h += " " * ((64 - (pre + len(h) + 1) % 64) % 64) + "\n"
    if version == 1:
        return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(h)) + h.encode() + payload
    return b"\x93NUMPY\x02\x00" + struct.pack("<I", len(h)) + h.encode() + payload


put("npy", "f4_2x3.npy", npy("<f4", (2, 3), struct.pack("<6f", 1, 2, 3, 4, 5, float("nan"))))
put("npy", "i4_4.npy", npy("<i4", (4,), struct.pack("<4i", -1, 0, 1, 2**31 - 1)))
put("npy", "u1_v2.npy", npy("|u1", (2, 2), bytes([0, 1, 2, 255]), version=2))
put("npy", "f8_scalar.npy", npy("<f8", (), struct.pack("<d", 3.5)).replace(b"(,)", b"()"))

# ------------------------------------------------------------------ alignment
put("align", "alignment.json", json.dumps({"origin": [678100.0, 5403800.0, 400.0], "scale": 0.37,
    "rotation": [[0, -1, 0], [1, 0, 0], [0, 0, 1]], "translation": [3, -1, 0.5]}))
put("align", "pairs.csv", "geo_x,geo_y,geo_z,scene_x,scene_y,scene_z\n0,0,0,1,2,3\n10,0,0,1,12,3\n0,10,0,-9,2,3\n0,0,10,1,2,13 # top\n")
put("align", "semantics.json", json.dumps({"entities": [
    {"id": 0, "object_id": "B1", "class": "Building", "level": "feature", "parent": None, "building": 0, "source": "a.gml", "lod": 3, "attributes": {}},
    {"id": 1, "object_id": "W1", "class": "WallSurface", "level": "surface", "parent": 0, "building": 0, "source": "a.gml", "lod": 3, "attributes": {"h": 1.5}},
    {"id": 2, "object_id": "O1", "class": "Window", "level": "part", "parent": 1, "building": 0, "source": "a.gml", "lod": None, "attributes": {}},
], "classes": [], "levels": ["feature", "surface", "part"]}))
