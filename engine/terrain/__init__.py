"""Terrain for every platform: ground points by the cloth simulation filter, a DEM (median ground
height per cell) and heights above ground. Frames: the input cloud's own; units: metres."""

from .dem import Dem, TerrainModel, TerrainParams, build_dem, classify_ground, lowest_points_dem, terrain_model

__all__ = ["Dem", "TerrainModel", "TerrainParams", "build_dem", "classify_ground", "lowest_points_dem", "terrain_model"]
