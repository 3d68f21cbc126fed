"""``mocapd view``: the live view's server (aiohttp), the pure state it shows and its page
(``static/``: HTML, JavaScript and CSS, no build step); docs/view.md."""
