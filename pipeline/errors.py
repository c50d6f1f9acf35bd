"""User-facing errors: the CLI prints them as one line and exits with code 2."""


class PipelineError(Exception):
    """Bad input from the user (target, params, store, graph). One line, exit 2."""


class NodeFailed(Exception):
    """A node's own function raised; the CLI shows its traceback and exits 1."""

    def __init__(self, instance: str, message: str, traceback_text: str = ""):
        super().__init__(f"node {instance} failed: {message}")
        self.instance = instance
        self.traceback_text = traceback_text
