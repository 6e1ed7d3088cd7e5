"""Errors the API reports as they are: an HTTP status and a message saying what is wrong."""

from __future__ import annotations


class ApiError(Exception):
    """An error the API reports as-is: HTTP status and a message saying what is wrong."""

    status = 400

    def __init__(self, message: str) -> None:
        super().__init__(message)
        self.message = message


class BadRequest(ApiError):
    status = 400


class NotFound(ApiError):
    status = 404


class Conflict(ApiError):
    status = 409


class Unprocessable(ApiError):
    status = 422


class TooMany(ApiError):
    status = 429
