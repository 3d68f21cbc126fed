"""The learning stack: motion templates learned from labelled examples (:mod:`.templates`), their
retrieval thresholds and keyframe gates calibrated on left-out actors (:mod:`.calibration`), and whole
libraries learned and written (:mod:`.library`), as ``mocapd learn`` does it. The runtime (reading
recordings and poses, features, the automaton, DTW, the live recogniser and loading a library)
imports nothing from here."""
