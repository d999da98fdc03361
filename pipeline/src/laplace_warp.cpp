// placeholder, filled in by the current work
