<?xml version="1.0" encoding="ISO-8859-1"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:bldg="http://www.opengis.net/citygml/building/2.0" xmlns:gml="http://www.opengis.net/gml">
<gml:name>München Straße</gml:name>
<core:cityObjectMember>
<bldg:Building gml:id="B1">
<gml:name>Häuser</gml:name>
<bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember><gml:Polygon gml:id="P1"><gml:exterior><gml:LinearRing>
<gml:posList srsDimension="3">0 0 0 1 0 0 1 1 0 0 0 x</gml:posList>
</gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod3MultiSurface>
</bldg:Building>
</core:cityObjectMember>
</core:CityModel>
