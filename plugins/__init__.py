"""pluggy hook specifications and the built-in plugins (project name ``hil``)."""
