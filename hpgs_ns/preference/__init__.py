"""The HP-GS human-preference model: pairs CSVs, training, evaluation and the labelling page."""
