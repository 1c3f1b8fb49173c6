"""Panoramas: a recording's frames stitched with an estimate (`recording`), the stitching itself
(`stitching`), the camera simulator (`camsim`) and the pixel grid (`equirect`)."""
