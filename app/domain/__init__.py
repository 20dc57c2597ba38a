"""The domain core: the paper's pipeline in plain Python (numpy, gtsam, networkx; no web framework,
no database, no plotting). Its packages are the pipeline's stages, each importing only earlier ones:

    errors, frames, json_values   shared by every stage: errors, rigid transforms, JSON helpers
    upload/       a phone's mapping session (and the 2020–21 format) read into typed arrays
    mapping/      graph SLAM on one walk or on a building's walks: screening, keyframes, optimizer
    navigation/   where a person can walk: path graph, corridor skeleton, routes, instructions
    localize/     a navigating phone placed in a map whose tags are held fixed
    evaluation/   how good a map is: metrics, ground truth, tuning sweeps, simulated sessions
    formats/      what the core reads and writes: our map JSON, the app's map file and a model of
                  how the app reads it, a Firebase export, what a version derives once

``tests/unit/test_layering.py`` holds the order: a stage never imports a later one (``localize``
and ``evaluation`` are siblings: neither imports the other).
"""
