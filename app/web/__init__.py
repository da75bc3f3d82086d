"""The web app: layout, controller, presenter, panels and the shared session (viser)."""
