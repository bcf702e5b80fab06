<?xml version="1.0" encoding="ISO-8859-1"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:bldg="http://www.opengis.net/citygml/building/2.0" xmlns:gen="http://www.opengis.net/citygml/generics/2.0" xmlns:app="http://www.opengis.net/citygml/appearance/2.0" xmlns:gml="http://www.opengis.net/gml" xmlns:xlink="http://www.w3.org/1999/xlink">
<gml:boundedBy><gml:Envelope srsName="EPSG:25832" srsDimension="3"><gml:lowerCorner>0 0 0</gml:lowerCorner><gml:upperCorner>10 8 6</gml:upperCorner></gml:Envelope></gml:boundedBy>
<core:cityObjectMember><bldg:Building gml:id="B1">
<gml:name>Häuser</gml:name>
<gen:stringAttribute name="note"><gen:value>x</gen:value></gen:stringAttribute>
<gen:doubleAttribute name="h"><gen:value>6.5</gen:value></gen:doubleAttribute>
<bldg:measuredHeight uom="m">6.0</bldg:measuredHeight>
<bldg:lod3Solid><gml:Solid><gml:exterior><gml:CompositeSurface>
<gml:surfaceMember xlink:href="#P1"/><gml:surfaceMember xlink:href="#P2"/>
</gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod3Solid>
<bldg:boundedBy><bldg:WallSurface gml:id="W1"><bldg:lod3MultiSurface><gml:MultiSurface><gml:surfaceMember>
<gml:Polygon gml:id="P1"><gml:exterior><gml:LinearRing gml:id="R1"><gml:posList srsDimension="3">0 0 0 10 0 0 10 0 6 0 0 6 0 0 0</gml:posList></gml:LinearRing></gml:exterior>
<gml:interior><gml:LinearRing><gml:posList>2 0 1 2 0 2 4 0 2 4 0 1 2 0 1</gml:posList></gml:LinearRing></gml:interior></gml:Polygon>
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
