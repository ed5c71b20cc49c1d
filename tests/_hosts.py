"""Tiny twin hosts for testing the process runner."""

import os


class EchoHost:
    def __init__(self, greeting: str) -> None:
        self.greeting = greeting

    def start(self):
        return {"greeting": self.greeting}

    def stop(self):
        pass

    def control(self, command, **kwargs):
        if command == "pid":
            return os.getpid()
        if command == "echo":
            return kwargs["value"]
        raise RuntimeError("boom")


class BrokenHost:
    def start(self):
        raise RuntimeError("refuses to start")

    def stop(self):
        pass
