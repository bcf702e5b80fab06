#!/usr/bin/env python3
"""Independent check of `gs4city query` attribute selections, straight from the CityGML files.

Reads CityGML 1.0/2.0/3.0 files with the standard library's ElementTree (no gs4city code), finds
every Building / BuildingPart, takes its own attribute (a direct child element `<ns:NAME>`, or a
generic attribute `<gen:*Attribute name="NAME"><gen:value>`) or, without one, the nearest enclosing
Building / BuildingPart's (the inheritance rule of docs/query.md), and prints as JSON the gml:ids of
the features whose value satisfies `NAME OP VALUE` and the "roots" among them (those whose
enclosing feature is not selected).

    python3 scripts/query_attr_check.py --name measuredHeight --op '>' --value 15 FILE.gml ...
"""
import argparse
import json
import operator
import sys
import xml.etree.ElementTree as ET

OPS = {"=": operator.eq, "!=": operator.ne, "<": operator.lt, "<=": operator.le,
       ">": operator.gt, ">=": operator.ge}
FEATURES = {"Building", "BuildingPart"}
GML_ID = "{http://www.opengis.net/gml}id"
GML32_ID = "{http://www.opengis.net/gml/3.2}id"


def local(tag):
    return tag.rsplit("}", 1)[-1]


def own_value(elem, name):
    for child in elem:
        tag = local(child.tag)
        if tag == name and child.text is not None:
            return child.text.strip()
        if tag.endswith("Attribute") and child.get("name") == name:
            for v in child:
                if local(v.tag) == "value" and v.text is not None:
                    return v.text.strip()
    return None


def walk(elem, inherited, parent_selected, name, test, out):
    tag = local(elem.tag)
    if tag in FEATURES:
        own = own_value(elem, name)
        value = own if own is not None else inherited
        selected = value is not None and test(value)
        gid = elem.get(GML_ID) or elem.get(GML32_ID)
        if selected:
            out["selected"].append(gid)
            if not parent_selected:
                out["roots"].append(gid)
        inherited, parent_selected = value, selected
    for child in elem:
        walk(child, inherited, parent_selected, name, test, out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--name", required=True)
    ap.add_argument("--op", required=True, choices=sorted(OPS))
    ap.add_argument("--value", required=True)
    ap.add_argument("files", nargs="+")
    a = ap.parse_args()
    op = OPS[a.op]

    def test(v):
        try:
            return op(float(v), float(a.value))
        except ValueError:
            return op(v, a.value)

    out = {"selected": [], "roots": []}
    for f in a.files:
        walk(ET.parse(f).getroot(), None, False, a.name, test, out)
    json.dump(out, sys.stdout, indent=1)
    print()


if __name__ == "__main__":
    main()
