"""The probe and the tissue: calibration, lens, force model, tissue fits and the rectification they give."""
