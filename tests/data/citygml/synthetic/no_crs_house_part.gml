<?xml version="1.0" encoding="UTF-8" standalone="no" ?>
<!-- Synthetic test data written by tests/data/citygml/synthetic/make_synthetic.py -->
<CityModel xmlns="http://www.opengis.net/citygml/2.0"
  xmlns:bldg="http://www.opengis.net/citygml/building/2.0"
  xmlns:core="http://www.opengis.net/citygml/base/2.0"
  xmlns:gml="http://www.opengis.net/gml"
  xmlns:xlink="http://www.w3.org/1999/xlink">
  <gml:name>a house without a CRS</gml:name>
  <gml:boundedBy>
    <gml:Envelope srsDimension="3">
      <gml:lowerCorner>1841513.129 5175885.000 197.400</gml:lowerCorner>
      <gml:upperCorner>1841528.197 5175895.155 207.800</gml:upperCorner>
    </gml:Envelope>
  </gml:boundedBy>
  <cityObjectMember>
    <bldg:Building gml:id="SYN_H1">
      <creationDate>2017-04-05</creationDate>
      <bldg:consistsOfBuildingPart>
        <bldg:BuildingPart gml:id="SYN_H1_1">
          <bldg:measuredHeight uom="#m">10.400</bldg:measuredHeight>
          <bldg:lod2Solid>
            <gml:Solid>
              <gml:exterior>
                <gml:CompositeSurface>
                  <gml:surfaceMember xlink:href="#SYN_H1_1_poly1"/>
                  <gml:surfaceMember xlink:href="#SYN_H1_1_poly2"/>
                  <gml:surfaceMember xlink:href="#SYN_H1_1_poly3"/>
                  <gml:surfaceMember xlink:href="#SYN_H1_1_poly4"/>
                  <gml:surfaceMember xlink:href="#SYN_H1_1_poly5"/>
                  <gml:surfaceMember xlink:href="#SYN_H1_1_poly6"/>
                  <gml:surfaceMember xlink:href="#SYN_H1_1_poly7"/>
                </gml:CompositeSurface>
              </gml:exterior>
            </gml:Solid>
          </bldg:lod2Solid>
          <bldg:boundedBy>
            <bldg:GroundSurface>
              <bldg:lod2MultiSurface>
                <gml:MultiSurface srsDimension="3">
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_H1_1_poly1">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:posList>1841513.129 5175891.120 197.400 1841526.326 5175895.155 197.400 1841528.197 5175889.035 197.400 1841515.000 5175885.000 197.400 1841513.129 5175891.120 197.400</gml:posList>
                        </gml:LinearRing>
                      </gml:exterior>
                    </gml:Polygon>
                  </gml:surfaceMember>
                </gml:MultiSurface>
              </bldg:lod2MultiSurface>
            </bldg:GroundSurface>
          </bldg:boundedBy>
          <bldg:boundedBy>
            <bldg:WallSurface>
              <bldg:lod2MultiSurface>
                <gml:MultiSurface srsDimension="3">
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_H1_1_poly2">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:posList>1841515.000 5175885.000 197.400 1841528.197 5175889.035 197.400 1841528.197 5175889.035 205.900 1841515.000 5175885.000 205.900 1841515.000 5175885.000 197.400</gml:posList>
                        </gml:LinearRing>
                      </gml:exterior>
                    </gml:Polygon>
                  </gml:surfaceMember>
                </gml:MultiSurface>
              </bldg:lod2MultiSurface>
            </bldg:WallSurface>
          </bldg:boundedBy>
          <bldg:boundedBy>
            <bldg:WallSurface>
              <bldg:lod2MultiSurface>
                <gml:MultiSurface srsDimension="3">
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_H1_1_poly3">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:posList>1841528.197 5175889.035 197.400 1841526.326 5175895.155 197.400 1841526.326 5175895.155 205.900 1841527.262 5175892.095 207.800 1841528.197 5175889.035 205.900 1841528.197 5175889.035 197.400</gml:posList>
                        </gml:LinearRing>
                      </gml:exterior>
                    </gml:Polygon>
                  </gml:surfaceMember>
                </gml:MultiSurface>
              </bldg:lod2MultiSurface>
            </bldg:WallSurface>
          </bldg:boundedBy>
          <bldg:boundedBy>
            <bldg:WallSurface>
              <bldg:lod2MultiSurface>
                <gml:MultiSurface srsDimension="3">
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_H1_1_poly4">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:posList>1841526.326 5175895.155 197.400 1841513.129 5175891.120 197.400 1841513.129 5175891.120 205.900 1841526.326 5175895.155 205.900 1841526.326 5175895.155 197.400</gml:posList>
                        </gml:LinearRing>
                      </gml:exterior>
                    </gml:Polygon>
                  </gml:surfaceMember>
                </gml:MultiSurface>
              </bldg:lod2MultiSurface>
            </bldg:WallSurface>
          </bldg:boundedBy>
          <bldg:boundedBy>
            <bldg:WallSurface>
              <bldg:lod2MultiSurface>
                <gml:MultiSurface srsDimension="3">
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_H1_1_poly5">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:posList>1841513.129 5175891.120 197.400 1841515.000 5175885.000 197.400 1841515.000 5175885.000 205.900 1841514.064 5175888.060 207.800 1841513.129 5175891.120 205.900 1841513.129 5175891.120 197.400</gml:posList>
                        </gml:LinearRing>
                      </gml:exterior>
                    </gml:Polygon>
                  </gml:surfaceMember>
                </gml:MultiSurface>
              </bldg:lod2MultiSurface>
            </bldg:WallSurface>
          </bldg:boundedBy>
          <bldg:boundedBy>
            <bldg:RoofSurface>
              <bldg:lod2MultiSurface>
                <gml:MultiSurface srsDimension="3">
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_H1_1_poly6">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:posList>1841515.000 5175885.000 205.900 1841528.197 5175889.035 205.900 1841527.262 5175892.095 207.800 1841514.064 5175888.060 207.800 1841515.000 5175885.000 205.900</gml:posList>
                        </gml:LinearRing>
                      </gml:exterior>
                    </gml:Polygon>
                  </gml:surfaceMember>
                </gml:MultiSurface>
              </bldg:lod2MultiSurface>
            </bldg:RoofSurface>
          </bldg:boundedBy>
          <bldg:boundedBy>
            <bldg:RoofSurface>
              <bldg:lod2MultiSurface>
                <gml:MultiSurface srsDimension="3">
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_H1_1_poly7">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:posList>1841526.326 5175895.155 205.900 1841513.129 5175891.120 205.900 1841514.064 5175888.060 207.800 1841527.262 5175892.095 207.800 1841526.326 5175895.155 205.900</gml:posList>
                        </gml:LinearRing>
                      </gml:exterior>
                    </gml:Polygon>
                  </gml:surfaceMember>
                </gml:MultiSurface>
              </bldg:lod2MultiSurface>
            </bldg:RoofSurface>
          </bldg:boundedBy>
        </bldg:BuildingPart>
      </bldg:consistsOfBuildingPart>
    </bldg:Building>
  </cityObjectMember>
</CityModel>
