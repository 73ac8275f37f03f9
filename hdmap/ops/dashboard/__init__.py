"""``hdmap dashboard``: a live operator view of the map and the services.

:mod:`.geometry` computes what is drawn (ellipses, facing arrows, GeoJSON, the health
panel's rows; pure), :mod:`.view` keeps what the dashboard has seen (current features,
each landmark's bounded history; no I/O), :mod:`.server` wires the bus and the HTTP
server. ``static/`` is the page and MapLibre GL JS (vendored, BSD-3-Clause, see
``static/MAPLIBRE-LICENSE.txt``): it works offline, with no tile server or CDN.
"""
