"""Movies of a trained scene: keyframed camera and parameter paths (``path``), the frames they
describe, movie files (``movie``) and the ``visnerf animate`` command (``commands``)."""
