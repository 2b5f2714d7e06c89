"""The mosaic: the canvas of weighted sums, its layer images and its Deep Zoom pyramid."""
