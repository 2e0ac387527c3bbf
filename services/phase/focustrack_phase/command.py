"""The `focustrack-phase` console script (and `python -m focustrack_phase`): the service, which
needs the extra `service`; without it, a message saying so."""

from focustrack_core.settings import main_of_extra

main = main_of_extra("focustrack-phase", "focustrack-phase[service]", "focustrack_phase.service")
