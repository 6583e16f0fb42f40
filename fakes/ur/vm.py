"""A small URScript interpreter for the fake UR controller: it runs a program sent to the script
port the way the URScript manual describes it (functions, ``while``/``if``, lists, the motion
and register built-ins) and turns it into what the arm would do, one target per controller step.

Written from the URScript manual, independently of ``drivers/ur/script.py``: a rendering mistake
there moves the simulated arm wrongly here instead of being mirrored. The subset: ``def``,
``while``, ``if``/``elif``/``else``, ``global``/``local``, assignments to names and list
elements, ``return``/``break``/``continue``/``halt``, arithmetic and comparisons, and the
built-ins of ``urscript_machine.Machine``. Numbers are Python floats (the controller's are 32
bit).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from robid_link.fakes.ur.machine import Machine, ScriptError

__all__ = ["ScriptError", "Machine", "Program", "compile_program"]

#: loop iterations without a motion, sleep or sync before the controller calls it a hang
IDLE_LIMIT = 2_000_000
_TOKEN = re.compile(r"""\s*(?:(?P<num>(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?)
                      |(?P<name>[A-Za-z_][A-Za-z0-9_]*)|(?P<str>"[^"]*"|'[^']*')
                      |(?P<op>==|!=|<=|>=|[-+*/%<>=()\[\],:]))""", re.X)
_KEYWORDS = {"and", "or", "not", "True", "False", "def", "end", "while", "if", "elif", "else",
             "global", "local", "return", "break", "continue", "halt", "thread", "sec"}


# ----------------------------------------------------------------------------- parsing
class _Signal(Exception):
    pass


class _Break(_Signal):
    pass


class _Continue(_Signal):
    pass


class _Return(_Signal):
    def __init__(self, value: Any) -> None:
        self.value = value


class _Halt(_Signal):
    pass


class _Frame:
    __slots__ = ("vars", "glob")

    def __init__(self, glob: dict[str, Any]) -> None:
        self.vars: dict[str, Any] = {}
        self.glob = glob


Expr = Callable[[_Frame], Any]
Stmt = Callable[[_Frame], None]


def _tokens(line: str, lineno: int) -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    pos, text = 0, line.rstrip()
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            raise ScriptError(f"line {lineno}: cannot read {text[pos:pos + 20]!r}")
        pos = m.end()
        if m.group("num"):
            s = m.group("num")
            out.append(("num", float(s) if any(c in s for c in ".eE") else int(s)))
        elif m.group("name"):
            out.append(("name", m.group("name")))
        elif m.group("str"):
            out.append(("str", m.group("str")[1:-1]))
        elif m.group("op"):
            out.append(("op", m.group("op")))
    return out


def _either(a: Expr, b: Expr) -> Expr:
    return lambda f: bool(a(f)) or bool(b(f))


def _both(a: Expr, b: Expr) -> Expr:
    return lambda f: bool(a(f)) and bool(b(f))


class _Line:
    """The tokens of one statement line with a cursor (expression parsing)."""

    def __init__(self, toks: list[tuple[str, Any]], lineno: int, env: _Compiler) -> None:
        self.t, self.i, self.no, self.env = toks, 0, lineno, env

    def peek(self) -> tuple[str, Any] | None:
        return self.t[self.i] if self.i < len(self.t) else None

    def take(self, value: Any = None) -> tuple[str, Any]:
        tok = self.peek()
        if tok is None or (value is not None and tok[1] != value):
            raise ScriptError(f"line {self.no}: expected {value or 'more'}, got "
                              f"{tok[1] if tok else 'end of line'!r}")
        self.i += 1
        return tok

    def at(self, value: Any) -> bool:
        tok = self.peek()
        return tok is not None and tok[0] in ("op", "name") and tok[1] == value

    def done(self) -> None:
        tok = self.peek()
        if tok is not None:
            raise ScriptError(f"line {self.no}: unexpected {tok[1]!r}")

    # precedence climbing: or < and < not < comparison < + - < * / % < unary < postfix
    def expr(self) -> Expr:
        left = self.conj()
        while self.at("or"):
            self.take()
            left = _either(left, self.conj())
        return left

    def conj(self) -> Expr:
        left = self.neg()
        while self.at("and"):
            self.take()
            left = _both(left, self.neg())
        return left

    def neg(self) -> Expr:
        if self.at("not"):
            self.take()
            a = self.neg()
            return lambda f: not a(f)
        return self.compare()

    _CMP = {"==": lambda x, y: x == y, "!=": lambda x, y: x != y, "<": lambda x, y: x < y,
            ">": lambda x, y: x > y, "<=": lambda x, y: x <= y, ">=": lambda x, y: x >= y}
    _ARITH = {"+": lambda x, y: x + y, "-": lambda x, y: x - y, "*": lambda x, y: x * y,
              "/": lambda x, y: x / y, "%": lambda x, y: x % y}

    def compare(self) -> Expr:
        left = self.binary(("+", "-"), self.term)
        tok = self.peek()
        if tok and tok[0] == "op" and tok[1] in self._CMP:
            self.take()
            op, a, b = self._CMP[tok[1]], left, self.binary(("+", "-"), self.term)
            left = lambda f: op(a(f), b(f))  # noqa: E731
        return left

    def term(self) -> Expr:
        return self.binary(("*", "/", "%"), self.unary)

    def binary(self, ops: tuple[str, ...], sub: Callable[[], Expr]) -> Expr:
        left = sub()
        while (tok := self.peek()) and tok[0] == "op" and tok[1] in ops:
            self.take()
            left = self._arith(tok[1], left, sub())
        return left

    def _arith(self, sym: str, a: Expr, b: Expr) -> Expr:
        op, no = self._ARITH[sym], self.no

        def run(f: _Frame) -> Any:
            x, y = a(f), b(f)
            if isinstance(x, list) or isinstance(y, list) or isinstance(x, str):
                raise ScriptError(f"line {no}: '{sym}' on {type(x).__name__} and "
                                  f"{type(y).__name__}")
            try:
                return op(x, y)
            except ZeroDivisionError:
                raise ScriptError(f"line {no}: division by zero") from None
        return run

    def unary(self) -> Expr:
        if self.at("-"):
            self.take()
            a = self.unary()
            return lambda f: -a(f)
        if self.at("+"):
            self.take()
        return self.postfix()

    def postfix(self) -> Expr:
        node = self.atom()
        while self.at("["):
            self.take()
            idx = self.expr()
            self.take("]")
            node = self._index(node, idx)
        return node

    def _index(self, seq: Expr, idx: Expr) -> Expr:
        no = self.no

        def run(f: _Frame) -> Any:
            s, i = seq(f), idx(f)
            try:
                return s[i]
            except (IndexError, TypeError):
                raise ScriptError(f"line {no}: index {i!r} out of range") from None
        return run

    def atom(self) -> Expr:
        kind, value = self.take()
        if kind in ("num", "str"):
            return lambda f: value
        if kind == "op" and value == "(":
            inner = self.expr()
            self.take(")")
            return inner
        if kind == "op" and value == "[":
            items = self.items("]")
            return lambda f: [x(f) for x in items]
        if kind == "name" and value in ("True", "False"):
            return lambda f: value == "True"
        if kind == "name" and value == "p" and self.at("["):  # a pose literal
            self.take()
            items = self.items("]")
            return lambda f: [x(f) for x in items]
        if kind == "name" and value not in _KEYWORDS:
            if self.at("("):
                self.take()
                return self.env.call(value, *self.args(), self.no)
            return self.env.load(value, self.no)
        raise ScriptError(f"line {self.no}: unexpected {value!r}")

    def items(self, close: str) -> list[Expr]:
        out: list[Expr] = []
        while not self.at(close):
            out.append(self.expr())
            if not self.at(close):
                self.take(",")
        self.take(close)
        return out

    def args(self) -> tuple[list[Expr], dict[str, Expr]]:
        pos: list[Expr] = []
        kw: dict[str, Expr] = {}
        while not self.at(")"):
            tok = self.peek()
            nxt = self.t[self.i + 1] if self.i + 1 < len(self.t) else None
            if tok and tok[0] == "name" and nxt == ("op", "="):
                self.i += 2
                kw[str(tok[1])] = self.expr()
            else:
                pos.append(self.expr())
            if not self.at(")"):
                self.take(",")
        self.take(")")
        return pos, kw


# ----------------------------------------------------------------------------- statements
class _Compiler:
    """Lines → closures; functions defined with ``def`` and the machine's built-ins."""

    def __init__(self, lines: list[tuple[int, list[tuple[str, Any]]]],
                 builtins: dict[str, Callable[..., Any]]) -> None:
        self.lines, self.pos = lines, 0
        self.builtins = builtins
        self.functions: dict[str, tuple[list[str], list[Stmt]]] = {}
        self.machine: Machine | None = None

    def load(self, name: str, no: int) -> Expr:
        def run(f: _Frame) -> Any:
            try:
                return f.vars[name]
            except KeyError:
                pass
            try:
                return f.glob[name]
            except KeyError:
                raise ScriptError(f"line {no}: variable {name!r} is not defined") from None
        return run

    def call(self, name: str, pos: list[Expr], kw: dict[str, Expr], no: int) -> Expr:
        if name in self.builtins:
            table = self.builtins  # bound to the running machine by Program.run

            def run_builtin(f: _Frame) -> Any:
                try:
                    return table[name](*[a(f) for a in pos], **{k: v(f) for k, v in kw.items()})
                except TypeError as err:
                    raise ScriptError(f"line {no}: {name}: {err}") from None
            return run_builtin

        def run_user(f: _Frame) -> Any:
            if name not in self.functions:
                raise ScriptError(f"line {no}: unknown function {name!r}")
            params, body = self.functions[name]
            if kw or len(pos) != len(params):
                raise ScriptError(f"line {no}: {name} takes {len(params)} arguments")
            frame = _Frame(f.glob)
            frame.vars.update(zip(params, [a(f) for a in pos], strict=True))
            try:
                _run(body, frame)
            except _Return as ret:
                return ret.value
            return None
        return run_user

    # -- blocks
    def block(self, closers: tuple[str, ...]) -> tuple[list[Stmt], str]:
        """Statements up to a line starting with one of ``closers``; that keyword."""
        out: list[Stmt] = []
        while self.pos < len(self.lines):
            no, toks = self.lines[self.pos]
            head = toks[0][1] if toks[0][0] == "name" else None
            if head in closers:
                return out, str(head)
            self.pos += 1
            out.append(self.statement(no, toks))
        if closers:
            raise ScriptError(f"end of program: '{closers[0]}' missing")
        return out, ""

    def statement(self, no: int, toks: list[tuple[str, Any]]) -> Stmt:
        ln = _Line(toks, no, self)
        head = toks[0][1] if toks[0][0] == "name" else None
        if head == "def":
            return self._def(ln)
        if head == "while":
            ln.take()
            cond = ln.expr()
            ln.take(":")
            ln.done()
            body, _ = self.block(("end",))
            self.pos += 1
            return self._while(cond, body)
        if head == "if":
            return self._if(ln)
        if head in ("break", "continue", "halt", "return"):
            return self._jump(ln, str(head))
        if head in ("global", "local"):
            ln.take()
        return self._assign_or_call(ln)

    def _def(self, ln: _Line) -> Stmt:
        ln.take("def")
        _, name = ln.take()
        ln.take("(")
        params: list[str] = []
        while not ln.at(")"):
            params.append(str(ln.take()[1]))
            if not ln.at(")"):
                ln.take(",")
        ln.take(")")
        ln.take(":")
        ln.done()
        body, _ = self.block(("end",))
        self.pos += 1
        self.functions[str(name)] = (params, body)
        return lambda f: None

    def _while(self, cond: Expr, body: list[Stmt]) -> Stmt:
        def run(f: _Frame) -> None:
            machine = self.machine
            while cond(f):
                if machine is not None:
                    machine.idle += 1
                    if machine.idle > IDLE_LIMIT:
                        raise ScriptError("infinite loop detected (no motion, sleep or sync)")
                try:
                    _run(body, f)
                except _Break:
                    break
                except _Continue:
                    continue
        return run

    def _if(self, ln: _Line) -> Stmt:
        branches: list[tuple[Expr, list[Stmt]]] = []
        ln.take("if")
        cond = ln.expr()
        ln.take(":")
        ln.done()
        while True:
            body, closer = self.block(("elif", "else", "end"))
            branches.append((cond, body))
            no, toks = self.lines[self.pos]
            self.pos += 1
            nxt = _Line(toks, no, self)
            nxt.take()
            if closer == "end":
                nxt.done()
                break
            if closer == "else":
                nxt.take(":")
                nxt.done()
                body, _ = self.block(("end",))
                self.pos += 1
                branches.append((lambda f: True, body))
                break
            cond = nxt.expr()
            nxt.take(":")
            nxt.done()

        def run(f: _Frame) -> None:
            for test, stmts in branches:
                if test(f):
                    _run(stmts, f)
                    return
        return run

    def _jump(self, ln: _Line, head: str) -> Stmt:
        ln.take()
        if head == "return":
            value = None if ln.peek() is None else ln.expr()
            ln.done()

            def ret(f: _Frame) -> None:
                raise _Return(value(f) if value else None)
            return ret
        ln.done()
        signal = {"break": _Break, "continue": _Continue, "halt": _Halt}[head]

        def jump(f: _Frame) -> None:
            raise signal()
        return jump

    def _assign_or_call(self, ln: _Line) -> Stmt:
        toks = ln.t
        if _assignment_at(toks) is None:
            value = ln.expr()
            ln.done()
            return lambda f: value(f)  # noqa: PLW0108  # a call for its effect
        if toks[0][0] != "name" or toks[0][1] in _KEYWORDS:
            raise ScriptError(f"line {ln.no}: cannot assign to {toks[0][1]!r}")
        name = str(toks[0][1])
        ln.take()
        index: Expr | None = None
        if ln.at("["):
            ln.take()
            index = ln.expr()
            ln.take("]")
        ln.take("=")
        value = ln.expr()
        ln.done()
        if index is None:
            def assign(f: _Frame) -> None:
                f.vars[name] = value(f)
            return assign
        target, no = self.load(name, ln.no), ln.no

        def assign_item(f: _Frame) -> None:
            seq, i = target(f), index(f)
            try:
                seq[i] = value(f)
            except (IndexError, TypeError):
                raise ScriptError(f"line {no}: {name}[{i!r}] cannot be assigned") from None
        return assign_item


def _assignment_at(toks: list[tuple[str, Any]]) -> int | None:
    """Where the statement's ``=`` is (outside brackets: not a keyword argument's)."""
    depth = 0
    for k, (kind, value) in enumerate(toks):
        if kind != "op":
            continue
        if value in "([":
            depth += 1
        elif value in ")]":
            depth -= 1
        elif value == "=" and depth == 0:
            return k
    return None


def _run(stmts: list[Stmt], f: _Frame) -> None:
    for s in stmts:
        s(f)


@dataclass
class Program:
    """A compiled program: ``name`` (its ``def``, or ``unnamed``) and how to run it."""

    name: str
    _compiler: _Compiler
    _body: list[Stmt]

    def run(self, machine: Machine) -> Machine:
        """Execute on ``machine`` (its built-ins bound anew); ScriptError on a runtime error."""
        comp = self._compiler
        comp.builtins.update(machine.builtins())
        comp.machine = machine
        frame = _Frame({})
        try:
            if self.name in comp.functions:
                comp.call(self.name, [], {}, 0)(frame)
            else:
                _run(self._body, frame)
        except _Halt:
            pass
        except (_Break, _Continue, _Return):
            raise ScriptError("break, continue or return outside their place") from None
        except RecursionError:
            raise ScriptError("recursion too deep") from None
        return machine


def compile_program(text: str) -> Program:
    """Parse a program (``def name(): … end``, or plain statements); ScriptError with the
    line number on a syntax error, as the controller refuses such a program."""
    lines: list[tuple[int, list[tuple[str, Any]]]] = []
    for no, raw in enumerate(text.splitlines(), 1):
        code = _strip_comment(raw)
        if code.strip():
            lines.append((no, _tokens(code, no)))
    placeholder = Machine([0.0] * 6)
    comp = _Compiler(lines, placeholder.builtins())
    body, _ = comp.block(())
    first = lines[0][1] if lines else []
    name = str(first[1][1]) if len(first) > 1 and first[0] == ("name", "def") else "unnamed"
    if name != "unnamed" and len(comp.functions) and name not in comp.functions:
        raise ScriptError(f"program {name} not defined")
    return Program(name, comp, body)


def _strip_comment(line: str) -> str:
    quote = None
    for k, ch in enumerate(line):
        if quote:
            quote = None if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch == "#":
            return line[:k]
    return line
