from collections.abc import Callable

FUNCTIONS: tuple[str, ...]

class Router:
    workers: int
    def __init__(
        self,
        functions: dict[str, int],
        source: int,
        sinks: list[int],
        choose: Callable[[bytes], int],
        cached: int,
    ) -> None: ...
    def drain(self, most: int) -> tuple[int, list[int]]: ...
