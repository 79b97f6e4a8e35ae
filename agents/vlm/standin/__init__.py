"""agos.agents.vlm.standin: ``agos vlm-standin``, an OpenAI-compatible chat-completion server on
loopback, for tests, the demo and new users who have no model.

One concern per module:

* :mod:`~agos.agents.vlm.standin.requests`: a chat-completion body validated, its token estimate;
* :mod:`~agos.agents.vlm.standin.schema`: the JSON Schema subset of a strict ``response_format``, and
  whether an answer conforms to it;
* :mod:`~agos.agents.vlm.standin.faults`: the fault model (kinds, probabilities, seeded draws);
* :mod:`~agos.agents.vlm.standin.replies`: the content each outcome gives, the completion object;
* :mod:`~agos.agents.vlm.standin.server`: the HTTP server (:class:`~agos.agents.vlm.standin.server.StandinServer`);
* :mod:`~agos.agents.vlm.standin.brain`: the default responder (OpenCV on the request, no ground truth);
* :mod:`~agos.agents.vlm.standin.perception`: what the brain sees: the heuristic's detectors fed with
  the request's RGB images, camera poses and references (no depth image);
* :mod:`~agos.agents.vlm.standin.command`: the ``vlm-standin`` command's parser and run.

The transport half is the server; the decisions come from a *responder*: a callable that takes the
request taken apart by :func:`agos.agents.vlm.protocol.split_request` and returns the reply object
(e.g. ``{"action": "WAIT", "reason": "..."}``). By default it is
``agos.agents.vlm.standin.brain.respond``, imported when the server is built.

Endpoints (under ``/v1``, as vLLM and SGLang serve them):

* ``GET /v1/models``: the configured model names in OpenAI list format.
* ``POST /v1/chat/completions``: an OpenAI ``chat.completion`` object; ``usage.prompt_tokens`` is
  estimated as text characters / 4 plus, per image, one token per 28x28 pixels (each side rounded
  to a multiple of 28, as Qwen2.5-VL does); ``completion_tokens`` as reply characters / 4.
  Errors use OpenAI's ``{"error": {"message", "type", "param", "code"}}`` body with OpenAI's types
  (``invalid_request_error``, ``authentication_error``, ``rate_limit_error``, ``server_error``) and
  a string or null ``code``: an unknown model is a 404 naming it (``model_not_found``), a malformed
  body a 400 saying what is wrong, more images than ``max_images`` a 400 whose message starts like
  vLLM's (``At most N image(s) may be provided in one prompt.``). With ``response_format``
  (``json_schema`` or ``json_object``) the content is plain JSON; without it the JSON is wrapped as
  models often do (markdown fences, a leading sentence) with probability ``wrap_p``. A ``json_schema``
  with ``strict: true`` is honoured or refused: a schema outside :mod:`~agos.agents.vlm.standin.schema`'s
  subset, or an answer of the responder that does not conform to it, is a 400 saying where (a
  non-strict schema is a hint, as in OpenAI's non-strict mode). ``n`` (1 to 128) gives ``n``
  choices, the same answer each wrapped by its own draw. ``max_tokens`` is honoured: a longer reply
  is cut and ends with ``finish_reason="length"``.
* ``GET /stats``: request, outcome and error counts (see :meth:`StandinServer.stats`).

With ``api_key`` (``agos vlm-standin --api-key-env NAME``) every ``/v1`` request must carry
``Authorization: Bearer <key>``; one without it gets a 401 (``authentication_error``,
``missing_api_key``), a wrong key a 401 (``invalid_api_key``) that never echoes it; ``/stats`` stays
open. A refused request draws no outcome.

Latency and faults are drawn per valid chat-completion request, in arrival order, from RNGs seeded
by ``seed``: the same seed and request order give the same outcomes and reply texts. Requests
refused on arrival (400/401/404) draw nothing; an answer refused by a strict schema was drawn.
Outcomes (``FAULT_KINDS`` plus ``"ok"``):

* ``ok``: the responder's JSON after ``latency_ms`` + U(0, ``jitter_ms``) (the responder's own time
  counts toward it).
* ``429``: at once, with ``Retry-After`` (seconds) and ``retry-after-ms`` headers (``retry_after_s``).
* ``500``: at once, an OpenAI-style server error.
* ``timeout``: the answer comes after ``hang_s`` (a client with a shorter timeout gives up; the late
  answer is then written to a closed connection and dropped).
* ``malformed``: 200 whose content is not JSON (truncated JSON or prose).
* ``fenced``: 200 with the JSON inside markdown fences followed by a sentence.
* ``empty``: 200 with content ``""`` or ``null``.
* ``length``: 200 with ``finish_reason="length"`` and truncated JSON.
* ``garbage``: 200 whose HTTP body is an HTML page, not JSON (a proxy's error page).

The server is a ``ThreadingHTTPServer`` (HTTP/1.1, keep-alive): every connection has its own thread,
so sleeps never hold up other requests, and the responder is called from several threads at once.
Each answer is one write on a ``TCP_NODELAY`` socket, so back-to-back requests on one keep-alive
connection take well under a millisecond each (two writes cost ~44 ms a request: Nagle's algorithm
waiting for the client's delayed ACK).
"""
