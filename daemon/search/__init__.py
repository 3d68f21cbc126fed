"""Content-based search of recorded motion (thesis chs. 2 to 4): segment codes (:mod:`.segments`), the
inverted-list index (:mod:`.index`) and its files (:mod:`.store`), keyframe search with stiffness
(:mod:`.keyframes`) and ranked template retrieval (:mod:`.retrieval`). ``mocapd search``'s engine;
the live recogniser imports nothing from here."""
