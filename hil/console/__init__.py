"""The operator console (``hil console``): a textual TUI over the controller. Needs the
``console`` extra (textual). See docs/console.md."""
