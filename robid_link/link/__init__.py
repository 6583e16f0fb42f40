"""The link: the asyncio daemon that drives campaigns through a controller driver."""
