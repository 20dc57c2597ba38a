"""Formats: what the core reads and writes beyond the upload.

map_io.py             our lossless map JSON, and the app's download format (§7)
app_model.py          a model of how the iPhone app decodes a map and plans a route
derived_documents.py  what a version derives once: the app's map file, the map page's overview
map_figure.py         what the map page plots, per floor
firebase_export.py    a lab's Firebase export, read into one list of maps
"""
