"""Contact-related entity API (get_contacts, get_links_net_contact_force, set_friction)."""


class ContactMixin:
    pass
