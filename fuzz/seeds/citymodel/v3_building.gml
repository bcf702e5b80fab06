<?xml version="1.0" encoding="UTF-8"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/3.0" xmlns:bldg="http://www.opengis.net/citygml/building/3.0" xmlns:con="http://www.opengis.net/citygml/construction/3.0" xmlns:gml="http://www.opengis.net/gml/3.2"><core:cityObjectMember><bldg:Building gml:id="B3">
<core:boundary><con:WallSurface gml:id="W3"><core:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember>
<gml:Polygon gml:id="P3"><gml:exterior><gml:LinearRing><gml:posList srsDimension="3">0 0 0 10 0 0 10 0 6 0 0 6 0 0 0</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon>
</gml:surfaceMember></gml:MultiSurface></core:lod3MultiSurface>
<con:fillingSurface><con:WindowSurface gml:id="WS3"><core:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember>
<gml:Polygon><gml:exterior><gml:LinearRing><gml:posList>2 0 1 2 0 2 4 0 2 4 0 1 2 0 1</gml:posList></gml:LinearRing></gml:exterior></gml:Polygon>
</gml:surfaceMember></gml:MultiSurface></core:lod3MultiSurface></con:WindowSurface></con:fillingSurface>
</con:WallSurface></core:boundary></bldg:Building></core:cityObjectMember></core:CityModel>
