"""Contacts (issue #4): placeholder until the contact model lands; no collision pairs -> None."""


class ContactSolver:
    @staticmethod
    def create(solver, models, options):
        return None
