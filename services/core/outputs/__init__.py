"""What a reconstruction gives people: documents, the report, plots, accuracy against a reference, DICOM."""
