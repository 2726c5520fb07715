"""egoslam.v1 messages, generated from proto/ by clients/python/generate_messages.py."""
