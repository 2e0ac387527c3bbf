"""The `focustrack-focus` console script (and `python -m focustrack_focus`): the service, which
needs the extra `service`; without it, a message saying so."""

from focustrack_core.settings import main_of_extra

main = main_of_extra("focustrack-focus", "focustrack-focus[service]", "focustrack_focus.service")
