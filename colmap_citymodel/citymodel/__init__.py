"""City model files -> PlaneStore (and back): CRSs, CityGML/CityJSON reading, the plane and vertex
store, CityGML and mesh writing."""
