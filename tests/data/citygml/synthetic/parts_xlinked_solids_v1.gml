<?xml version="1.0" encoding="UTF-8"?>
<!-- Synthetic test data written by tests/data/citygml/synthetic/make_synthetic.py -->
<CityModel xmlns="http://www.opengis.net/citygml/1.0"
  xmlns:bldg="http://www.opengis.net/citygml/building/1.0"
  xmlns:gml="http://www.opengis.net/gml"
  xmlns:xlink="http://www.w3.org/1999/xlink">
  <gml:name>one building of three parts</gml:name>
  <gml:boundedBy>
    <gml:Envelope srsName="urn:ogc:def:crs:EPSG::28992">
      <gml:lowerCorner>78592.000 457900.000 3.000</gml:lowerCorner>
      <gml:upperCorner>78616.000 457908.000 12.000</gml:upperCorner>
    </gml:Envelope>
  </gml:boundedBy>
  <cityObjectMember>
    <bldg:Building gml:id="SYN_B1">
      <bldg:consistsOfBuildingPart>
        <bldg:BuildingPart gml:id="SYN_B1_A">
          <bldg:lod2Solid>
            <gml:Solid>
              <gml:exterior>
                <gml:CompositeSurface>
                  <gml:surfaceMember xlink:href="#SYN_B1_A_1"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_A_2"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_A_3"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_A_4"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_A_5"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_A_6"/>
                </gml:CompositeSurface>
              </gml:exterior>
            </gml:Solid>
          </bldg:lod2Solid>
          <bldg:boundedBy>
            <bldg:GroundSurface>
              <bldg:lod2MultiSurface>
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_A_1">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78600.000 457908.000 3.000</gml:pos>
                          <gml:pos>78610.000 457908.000 3.000</gml:pos>
                          <gml:pos>78610.000 457900.000 3.000</gml:pos>
                          <gml:pos>78600.000 457900.000 3.000</gml:pos>
                          <gml:pos>78600.000 457908.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_A_2">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78600.000 457900.000 3.000</gml:pos>
                          <gml:pos>78610.000 457900.000 3.000</gml:pos>
                          <gml:pos>78610.000 457900.000 12.000</gml:pos>
                          <gml:pos>78600.000 457900.000 12.000</gml:pos>
                          <gml:pos>78600.000 457900.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_A_3">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78610.000 457900.000 3.000</gml:pos>
                          <gml:pos>78610.000 457908.000 3.000</gml:pos>
                          <gml:pos>78610.000 457908.000 12.000</gml:pos>
                          <gml:pos>78610.000 457900.000 12.000</gml:pos>
                          <gml:pos>78610.000 457900.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_A_4">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78610.000 457908.000 3.000</gml:pos>
                          <gml:pos>78600.000 457908.000 3.000</gml:pos>
                          <gml:pos>78600.000 457908.000 12.000</gml:pos>
                          <gml:pos>78610.000 457908.000 12.000</gml:pos>
                          <gml:pos>78610.000 457908.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_A_5">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78600.000 457908.000 3.000</gml:pos>
                          <gml:pos>78600.000 457900.000 3.000</gml:pos>
                          <gml:pos>78600.000 457900.000 12.000</gml:pos>
                          <gml:pos>78600.000 457908.000 12.000</gml:pos>
                          <gml:pos>78600.000 457908.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_A_6">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78600.000 457900.000 12.000</gml:pos>
                          <gml:pos>78610.000 457900.000 12.000</gml:pos>
                          <gml:pos>78610.000 457908.000 12.000</gml:pos>
                          <gml:pos>78600.000 457908.000 12.000</gml:pos>
                          <gml:pos>78600.000 457900.000 12.000</gml:pos>
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
      <bldg:consistsOfBuildingPart>
        <bldg:BuildingPart gml:id="SYN_B1_B">
          <bldg:lod2Solid>
            <gml:Solid>
              <gml:exterior>
                <gml:CompositeSurface>
                  <gml:surfaceMember xlink:href="#SYN_B1_B_1"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_B_2"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_B_3"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_B_4"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_B_5"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_B_6"/>
                </gml:CompositeSurface>
              </gml:exterior>
            </gml:Solid>
          </bldg:lod2Solid>
          <bldg:boundedBy>
            <bldg:GroundSurface>
              <bldg:lod2MultiSurface>
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_B_1">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78610.000 457908.000 3.000</gml:pos>
                          <gml:pos>78616.000 457908.000 3.000</gml:pos>
                          <gml:pos>78616.000 457900.000 3.000</gml:pos>
                          <gml:pos>78610.000 457900.000 3.000</gml:pos>
                          <gml:pos>78610.000 457908.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_B_2">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78610.000 457900.000 3.000</gml:pos>
                          <gml:pos>78616.000 457900.000 3.000</gml:pos>
                          <gml:pos>78616.000 457900.000 9.000</gml:pos>
                          <gml:pos>78610.000 457900.000 9.000</gml:pos>
                          <gml:pos>78610.000 457900.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_B_3">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78616.000 457900.000 3.000</gml:pos>
                          <gml:pos>78616.000 457908.000 3.000</gml:pos>
                          <gml:pos>78616.000 457908.000 9.000</gml:pos>
                          <gml:pos>78616.000 457900.000 9.000</gml:pos>
                          <gml:pos>78616.000 457900.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_B_4">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78616.000 457908.000 3.000</gml:pos>
                          <gml:pos>78610.000 457908.000 3.000</gml:pos>
                          <gml:pos>78610.000 457908.000 9.000</gml:pos>
                          <gml:pos>78616.000 457908.000 9.000</gml:pos>
                          <gml:pos>78616.000 457908.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_B_5">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78610.000 457908.000 3.000</gml:pos>
                          <gml:pos>78610.000 457900.000 3.000</gml:pos>
                          <gml:pos>78610.000 457900.000 9.000</gml:pos>
                          <gml:pos>78610.000 457908.000 9.000</gml:pos>
                          <gml:pos>78610.000 457908.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_B_6">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78610.000 457900.000 9.000</gml:pos>
                          <gml:pos>78616.000 457900.000 9.000</gml:pos>
                          <gml:pos>78616.000 457908.000 9.000</gml:pos>
                          <gml:pos>78610.000 457908.000 9.000</gml:pos>
                          <gml:pos>78610.000 457900.000 9.000</gml:pos>
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
      <bldg:consistsOfBuildingPart>
        <bldg:BuildingPart gml:id="SYN_B1_C">
          <bldg:lod2Solid>
            <gml:Solid>
              <gml:exterior>
                <gml:CompositeSurface>
                  <gml:surfaceMember xlink:href="#SYN_B1_C_1"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_C_2"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_C_3"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_C_4"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_C_5"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_C_6"/>
                  <gml:surfaceMember xlink:href="#SYN_B1_C_7"/>
                </gml:CompositeSurface>
              </gml:exterior>
            </gml:Solid>
          </bldg:lod2Solid>
          <bldg:boundedBy>
            <bldg:GroundSurface>
              <bldg:lod2MultiSurface>
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_C_1">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78592.000 457908.000 3.000</gml:pos>
                          <gml:pos>78600.000 457908.000 3.000</gml:pos>
                          <gml:pos>78600.000 457900.000 3.000</gml:pos>
                          <gml:pos>78592.000 457900.000 3.000</gml:pos>
                          <gml:pos>78592.000 457908.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_C_2">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78592.000 457900.000 3.000</gml:pos>
                          <gml:pos>78600.000 457900.000 3.000</gml:pos>
                          <gml:pos>78600.000 457900.000 9.000</gml:pos>
                          <gml:pos>78592.000 457900.000 9.000</gml:pos>
                          <gml:pos>78592.000 457900.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_C_3">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78600.000 457900.000 3.000</gml:pos>
                          <gml:pos>78600.000 457908.000 3.000</gml:pos>
                          <gml:pos>78600.000 457908.000 9.000</gml:pos>
                          <gml:pos>78600.000 457904.000 12.000</gml:pos>
                          <gml:pos>78600.000 457900.000 9.000</gml:pos>
                          <gml:pos>78600.000 457900.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_C_4">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78600.000 457908.000 3.000</gml:pos>
                          <gml:pos>78592.000 457908.000 3.000</gml:pos>
                          <gml:pos>78592.000 457908.000 9.000</gml:pos>
                          <gml:pos>78600.000 457908.000 9.000</gml:pos>
                          <gml:pos>78600.000 457908.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_C_5">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78592.000 457908.000 3.000</gml:pos>
                          <gml:pos>78592.000 457900.000 3.000</gml:pos>
                          <gml:pos>78592.000 457900.000 9.000</gml:pos>
                          <gml:pos>78592.000 457904.000 12.000</gml:pos>
                          <gml:pos>78592.000 457908.000 9.000</gml:pos>
                          <gml:pos>78592.000 457908.000 3.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_C_6">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78592.000 457900.000 9.000</gml:pos>
                          <gml:pos>78600.000 457900.000 9.000</gml:pos>
                          <gml:pos>78600.000 457904.000 12.000</gml:pos>
                          <gml:pos>78592.000 457904.000 12.000</gml:pos>
                          <gml:pos>78592.000 457900.000 9.000</gml:pos>
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
                <gml:MultiSurface>
                  <gml:surfaceMember>
                    <gml:Polygon gml:id="SYN_B1_C_7">
                      <gml:exterior>
                        <gml:LinearRing>
                          <gml:pos>78600.000 457908.000 9.000</gml:pos>
                          <gml:pos>78592.000 457908.000 9.000</gml:pos>
                          <gml:pos>78592.000 457904.000 12.000</gml:pos>
                          <gml:pos>78600.000 457904.000 12.000</gml:pos>
                          <gml:pos>78600.000 457908.000 9.000</gml:pos>
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
