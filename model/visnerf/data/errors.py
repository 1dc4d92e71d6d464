"""The error every dataset reader raises for input it refuses."""


class DatasetError(ValueError):
    """The dataset cannot be read; the message names the file and the problem."""
