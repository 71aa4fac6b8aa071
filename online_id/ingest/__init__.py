"""From recordings and frames to samples: the frame assembler, bench files and CAN logs read as bench data,
signal columns and their units."""
