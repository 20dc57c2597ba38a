"""Navigation: where a person can walk in a map, and what they hear on the way (§6, §8).

path_graph/          the graph's model, its JSON, GeoJSON and app links; the walked-line builder
skeleton.py          the corridor skeleton of one walk or fused from a building map's walks
                     (centreline.py, raster.py: its image steps)
floors.py            floors from height
routing.py           routes from a tag, place, node or position to another (shortest_path.py)
instructions/        turn-by-turn at decision points only (polyline.py: a route's geometry)
"""
