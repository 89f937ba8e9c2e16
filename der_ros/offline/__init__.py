"""Offline tools on recorded bags: episodes, export, training from bags, plots, rendering, playback, ``der bag``.

They stand on both :mod:`der_ros.bag` (MCAP files) and :mod:`der_ros.contract` (what the messages
mean). Kept import-light on purpose: import the submodule you need.
"""
