"""Mapping: graph SLAM on one walk (docs/architecture.md §3) or on a building's walks together.

params.py       SlamParams: noise and rejection thresholds, each with its unit
screening.py    which tag detections enter the factor graph, and why the others do not
keyframes.py    which phone poses the graph holds, and where the others go afterwards
slam/           the factor graph and its optimization (every gtsam call of the project)
joint/          several walks of one building optimized as one graph (a package, by step)
map_result.py   what an optimization produces: the map, its statistics, its rejections
uncertainty.py  a tag's horizontal position ellipse from its marginal covariance
"""
