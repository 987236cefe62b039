"""forestreg.plugin: thin host adapters (QGIS, CloudCompare) that run the CLI."""
