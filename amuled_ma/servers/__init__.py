"""LLM servers: addresses, the preflight, a pool of servers, request timing, a private server."""
