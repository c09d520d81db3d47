"""The application on top: the stage layer, the command line, the demo, the PLC service."""
