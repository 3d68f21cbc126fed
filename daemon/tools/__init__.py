"""Dataset preparation for the shipped library's build (``python -m bench.shipped_library``): the
training set of the shipped classes (:mod:`.shipped`), the CMU mocap6 runs cut into single
repetitions (:mod:`.mocap6`) and the repetition cutter itself (:mod:`.repetitions`). Neither the
runtime nor ``mocapd learn`` imports anything from here."""
