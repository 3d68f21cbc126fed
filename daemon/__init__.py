"""mocapd: the recognition engine and the service (features, index, keyframes, templates, CLI)."""
