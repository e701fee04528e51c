//! A minimal Python unpickler: enough of protocols 0–5 to read the pickles that hold pretrained weights
//! (numpy arrays pickled in nested dicts, PyTorch `.pth` / `.pt` files, TorchScript `data.pkl`).
//!
//! Nothing is executed: a `GLOBAL` becomes [`Value::Global`], and `REDUCE` / `NEWOBJ` / `BUILD` build an
//! [`Object`] that records the callable, its arguments and its state for the caller to interpret. Lists, dicts
//! and objects are shared (`Rc<RefCell<…>>`) so that a memoized container filled after it was memoized
//! (`EMPTY_DICT, BINPUT, MARK, …, SETITEMS`) is seen filled wherever it is referenced.

use std::cell::RefCell;
use std::collections::HashMap;
use std::rc::Rc;

/// Error of the unpickler: what went wrong and at which byte.
#[derive(Debug, Clone, PartialEq)]
pub struct PickleError {
    pub pos: usize,
    pub msg: String,
}

impl std::fmt::Display for PickleError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "pickle: {} at byte {}", self.msg, self.pos)
    }
}

impl std::error::Error for PickleError {}

type Result<T> = std::result::Result<T, PickleError>;

/// A Python value as far as the unpickler can tell.
#[derive(Debug, Clone)]
pub enum Value {
    None,
    Bool(bool),
    Int(i64),
    Float(f64),
    /// An integer too wide for i64: little-endian two's complement bytes.
    BigInt(Rc<Vec<u8>>),
    Str(String),
    Bytes(Rc<Vec<u8>>),
    Tuple(Rc<Vec<Value>>),
    List(Rc<RefCell<Vec<Value>>>),
    Dict(Rc<RefCell<Vec<(Value, Value)>>>),
    /// `module.name`, not resolved.
    Global {
        module: String,
        name: String,
    },
    /// The result of `REDUCE` / `NEWOBJ` (then maybe `BUILD`, `APPENDS`, `SETITEMS`).
    Object(Rc<RefCell<Object>>),
    /// A persistent id (`PERSID` / `BINPERSID`): PyTorch's reference to a tensor storage.
    PersId(Rc<Value>),
}

/// `callable(*args)`, then `__setstate__(state)` / `extend(list_items)` / `update(dict_items)`.
#[derive(Debug, Clone)]
pub struct Object {
    pub callable: Value,
    pub args: Value,
    pub state: Option<Value>,
    pub list_items: Vec<Value>,
    pub dict_items: Vec<(Value, Value)>,
}

impl Value {
    pub fn as_str(&self) -> Option<&str> {
        match self {
            Value::Str(s) => Some(s),
            _ => None,
        }
    }

    pub fn as_int(&self) -> Option<i64> {
        match self {
            Value::Int(i) => Some(*i),
            Value::Bool(b) => Some(*b as i64),
            _ => None,
        }
    }

    pub fn as_bool(&self) -> Option<bool> {
        match self {
            Value::Bool(b) => Some(*b),
            Value::Int(i) => Some(*i != 0),
            _ => None,
        }
    }

    /// Elements of a tuple or a list.
    pub fn items(&self) -> Option<Vec<Value>> {
        match self {
            Value::Tuple(t) => Some(t.as_ref().clone()),
            Value::List(l) => Some(l.borrow().clone()),
            _ => None,
        }
    }

    /// Key/value pairs of a dict; of an object: its [`Value::mapping_items`], else its state's pairs.
    pub fn pairs(&self) -> Option<Vec<(Value, Value)>> {
        match self {
            Value::Dict(d) => Some(d.borrow().clone()),
            Value::Object(o) => {
                let items = self.mapping_items();
                if !items.is_empty() {
                    return Some(items);
                }
                match &o.borrow().state {
                    Some(s @ Value::Dict(_)) => s.pairs(),
                    _ => Some(Vec::new()),
                }
            }
            _ => None,
        }
    }

    /// The items an object got as a mapping: `SETITEMS` on it, and for `OrderedDict([[k, v], …])` (old
    /// PyTorch files) the constructor's pairs.
    pub fn mapping_items(&self) -> Vec<(Value, Value)> {
        let Value::Object(o) = self else { return Vec::new() };
        let o = o.borrow();
        let mut pairs = Vec::new();
        if o.callable.class_name().as_deref() == Some("collections.OrderedDict") {
            if let Some(list) = o.args.items().and_then(|a| a.first().cloned()).and_then(|l| l.items()) {
                for kv in list {
                    if let Some([k, v]) = kv.items().as_deref() {
                        pairs.push((k.clone(), v.clone()));
                    }
                }
            }
        }
        pairs.extend(o.dict_items.iter().cloned());
        pairs
    }

    /// `self[key]` for a dict (or mapping object) with string keys.
    pub fn get(&self, key: &str) -> Option<Value> {
        self.pairs()?.into_iter().find(|(k, _)| k.as_str() == Some(key)).map(|(_, v)| v)
    }

    /// `module.name` of a global, or of the callable of an object.
    pub fn class_name(&self) -> Option<String> {
        match self {
            Value::Global { module, name } => Some(format!("{module}.{name}")),
            Value::Object(o) => o.borrow().callable.class_name(),
            _ => None,
        }
    }
}

/// Reads one pickle from the start of `data`; returns the value and the number of bytes consumed (files such
/// as PyTorch's legacy format hold several pickles back to back).
pub fn load(data: &[u8]) -> Result<(Value, usize)> {
    Unpickler { data, pos: 0, stack: Vec::new(), marks: Vec::new(), memo: HashMap::new() }.run()
}

struct Unpickler<'a> {
    data: &'a [u8],
    pos: usize,
    stack: Vec<Value>,
    marks: Vec<usize>,
    memo: HashMap<u64, Value>,
}

impl<'a> Unpickler<'a> {
    fn err<T>(&self, msg: impl Into<String>) -> Result<T> {
        Err(PickleError { pos: self.pos, msg: msg.into() })
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8]> {
        if self.data.len() - self.pos < n {
            return self.err(format!("truncated: {n} bytes wanted, {} left", self.data.len() - self.pos));
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }

    fn u8(&mut self) -> Result<u8> {
        Ok(self.take(1)?[0])
    }

    fn u16(&mut self) -> Result<u16> {
        Ok(u16::from_le_bytes(self.take(2)?.try_into().unwrap()))
    }

    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(self.take(4)?.try_into().unwrap()))
    }

    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(self.take(8)?.try_into().unwrap()))
    }

    fn line(&mut self) -> Result<&'a str> {
        let rest = &self.data[self.pos..];
        let Some(n) = rest.iter().position(|&b| b == b'\n') else { return self.err("unterminated line") };
        let s = std::str::from_utf8(&rest[..n]).map_err(|_| PickleError { pos: self.pos, msg: "non-UTF-8 line".into() })?;
        self.pos += n + 1;
        Ok(s)
    }

    fn pop(&mut self) -> Result<Value> {
        if self.marks.last().is_some_and(|&m| m >= self.stack.len()) {
            return self.err("pop below the last mark");
        }
        match self.stack.pop() {
            Some(v) => Ok(v),
            None => self.err("pop from an empty stack"),
        }
    }

    fn top(&mut self) -> Result<&mut Value> {
        match self.stack.last_mut() {
            Some(v) => Ok(v),
            None => Err(PickleError { pos: self.pos, msg: "empty stack".into() }),
        }
    }

    fn pop_mark(&mut self) -> Result<Vec<Value>> {
        let Some(m) = self.marks.pop() else { return self.err("no mark") };
        if m > self.stack.len() {
            return self.err("mark above the stack");
        }
        Ok(self.stack.split_off(m))
    }

    fn memo_get(&self, key: u64) -> Result<Value> {
        match self.memo.get(&key) {
            Some(v) => Ok(v.clone()),
            None => self.err(format!("memo key {key} unset")),
        }
    }

    fn memo_put(&mut self, key: u64) -> Result<()> {
        let v = self.top()?.clone();
        self.memo.insert(key, v);
        Ok(())
    }

    fn append(&mut self, target: &Value, items: Vec<Value>) -> Result<()> {
        match target {
            Value::List(l) => l.borrow_mut().extend(items),
            Value::Object(o) => o.borrow_mut().list_items.extend(items),
            _ => return self.err("APPEND(S) to a non-list"),
        }
        Ok(())
    }

    fn set_items(&mut self, target: &Value, items: Vec<Value>) -> Result<()> {
        if items.len() & 1 != 0 {
            return self.err("SETITEMS with an odd number of items");
        }
        let mut it = items.into_iter();
        let mut pairs = Vec::new();
        while let (Some(k), Some(v)) = (it.next(), it.next()) {
            pairs.push((k, v));
        }
        match target {
            Value::Dict(d) => {
                let mut d = d.borrow_mut();
                for (k, v) in pairs {
                    // Later keys replace earlier equal string keys, like a Python dict.
                    if let Some(slot) = k.as_str().and_then(|ks| d.iter_mut().find(|(dk, _)| dk.as_str() == Some(ks))) {
                        slot.1 = v;
                    } else {
                        d.push((k, v));
                    }
                }
            }
            Value::Object(o) => o.borrow_mut().dict_items.extend(pairs),
            _ => return self.err("SETITEM(S) on a non-dict"),
        }
        Ok(())
    }

    fn object(callable: Value, args: Value) -> Value {
        Value::Object(Rc::new(RefCell::new(Object { callable, args, state: None, list_items: Vec::new(), dict_items: Vec::new() })))
    }

    /// Little-endian two's complement of at most 8 bytes.
    fn long(bytes: &[u8]) -> i64 {
        if bytes.is_empty() {
            return 0;
        }
        let neg = bytes[bytes.len() - 1] & 0x80 != 0;
        let mut buf = if neg { [0xffu8; 8] } else { [0u8; 8] };
        buf[..bytes.len()].copy_from_slice(bytes);
        i64::from_le_bytes(buf)
    }

    fn run(mut self) -> Result<(Value, usize)> {
        loop {
            let op = self.u8()?;
            match op {
                0x80 => {
                    let _proto = self.u8()?;
                }
                0x95 => {
                    let _frame_len = self.u64()?;
                }
                b'.' => {
                    let v = self.pop()?;
                    return Ok((v, self.pos));
                }
                b'(' => self.marks.push(self.stack.len()),
                b'0' => {
                    self.pop()?;
                }
                b'1' => {
                    self.pop_mark()?;
                }
                b'2' => {
                    let v = self.top()?.clone();
                    self.stack.push(v);
                }
                b'N' => self.stack.push(Value::None),
                0x88 => self.stack.push(Value::Bool(true)),
                0x89 => self.stack.push(Value::Bool(false)),
                b'I' => {
                    let l = self.line()?;
                    let v = match l {
                        "01" => Value::Bool(true),
                        "00" => Value::Bool(false),
                        _ => Value::Int(l.parse().map_err(|_| PickleError { pos: self.pos, msg: format!("INT {l:?}") })?),
                    };
                    self.stack.push(v);
                }
                b'L' => {
                    let l = self.line()?.trim_end_matches('L');
                    let v = l.parse().map_err(|_| PickleError { pos: self.pos, msg: format!("LONG {l:?}") })?;
                    self.stack.push(Value::Int(v));
                }
                b'F' => {
                    let l = self.line()?;
                    let v = l.parse().map_err(|_| PickleError { pos: self.pos, msg: format!("FLOAT {l:?}") })?;
                    self.stack.push(Value::Float(v));
                }
                b'J' => {
                    let v = self.u32()? as i32;
                    self.stack.push(Value::Int(v as i64));
                }
                b'K' => {
                    let v = self.u8()?;
                    self.stack.push(Value::Int(v as i64));
                }
                b'M' => {
                    let v = self.u16()?;
                    self.stack.push(Value::Int(v as i64));
                }
                0x8a | 0x8b => {
                    let n = if op == 0x8a { self.u8()? as usize } else { self.u32()? as usize };
                    let b = self.take(n)?;
                    let v = if n <= 8 { Value::Int(Self::long(b)) } else { Value::BigInt(Rc::new(b.to_vec())) };
                    self.stack.push(v);
                }
                b'G' => {
                    let v = f64::from_be_bytes(self.take(8)?.try_into().unwrap());
                    self.stack.push(Value::Float(v));
                }
                b'X' | 0x8c | 0x8d => {
                    let n = match op {
                        b'X' => self.u32()? as usize,
                        0x8c => self.u8()? as usize,
                        _ => self.u64()? as usize,
                    };
                    let b = self.take(n)?;
                    let s = String::from_utf8(b.to_vec()).map_err(|_| PickleError { pos: self.pos, msg: "non-UTF-8 str".into() })?;
                    self.stack.push(Value::Str(s));
                }
                b'T' | b'U' => {
                    // Python 2 `str`: bytes that Python 3 decodes as text (latin-1 keeps every byte).
                    let n = if op == b'T' { self.u32()? as usize } else { self.u8()? as usize };
                    let b = self.take(n)?;
                    self.stack.push(Value::Str(b.iter().map(|&c| c as char).collect()));
                }
                b'C' | b'B' | 0x8e | 0x96 => {
                    let n = match op {
                        b'C' => self.u8()? as usize,
                        b'B' => self.u32()? as usize,
                        _ => self.u64()? as usize,
                    };
                    let b = self.take(n)?;
                    self.stack.push(Value::Bytes(Rc::new(b.to_vec())));
                }
                b')' => self.stack.push(Value::Tuple(Rc::new(Vec::new()))),
                b't' => {
                    let items = self.pop_mark()?;
                    self.stack.push(Value::Tuple(Rc::new(items)));
                }
                0x85..=0x87 => {
                    let n = (op - 0x84) as usize;
                    if self.stack.len() < n || self.marks.last().is_some_and(|&m| m > self.stack.len() - n) {
                        return self.err("TUPLEn below the mark");
                    }
                    let items = self.stack.split_off(self.stack.len() - n);
                    self.stack.push(Value::Tuple(Rc::new(items)));
                }
                b']' => self.stack.push(Value::List(Rc::new(RefCell::new(Vec::new())))),
                b'l' => {
                    let items = self.pop_mark()?;
                    self.stack.push(Value::List(Rc::new(RefCell::new(items))));
                }
                b'a' => {
                    let v = self.pop()?;
                    let target = self.top()?.clone();
                    self.append(&target, vec![v])?;
                }
                b'e' => {
                    let items = self.pop_mark()?;
                    let target = self.top()?.clone();
                    self.append(&target, items)?;
                }
                b'}' => self.stack.push(Value::Dict(Rc::new(RefCell::new(Vec::new())))),
                b'd' => {
                    let items = self.pop_mark()?;
                    let d = Value::Dict(Rc::new(RefCell::new(Vec::new())));
                    self.set_items(&d, items)?;
                    self.stack.push(d);
                }
                b's' => {
                    let v = self.pop()?;
                    let k = self.pop()?;
                    let target = self.top()?.clone();
                    self.set_items(&target, vec![k, v])?;
                }
                b'u' => {
                    let items = self.pop_mark()?;
                    let target = self.top()?.clone();
                    self.set_items(&target, items)?;
                }
                0x8f => self.stack.push(Value::List(Rc::new(RefCell::new(Vec::new())))),
                0x90 => {
                    let items = self.pop_mark()?;
                    let target = self.top()?.clone();
                    self.append(&target, items)?;
                }
                0x91 => {
                    let items = self.pop_mark()?;
                    self.stack.push(Value::List(Rc::new(RefCell::new(items))));
                }
                b'c' => {
                    let module = self.line()?.to_string();
                    let name = self.line()?.to_string();
                    self.stack.push(Value::Global { module, name });
                }
                0x93 => {
                    let name = self.pop()?;
                    let module = self.pop()?;
                    match (module, name) {
                        (Value::Str(module), Value::Str(name)) => self.stack.push(Value::Global { module, name }),
                        _ => return self.err("STACK_GLOBAL of non-strings"),
                    }
                }
                b'R' | 0x81 => {
                    let args = self.pop()?;
                    let callable = self.pop()?;
                    self.stack.push(Self::object(callable, args));
                }
                0x92 => {
                    let _kwargs = self.pop()?;
                    let args = self.pop()?;
                    let callable = self.pop()?;
                    self.stack.push(Self::object(callable, args));
                }
                b'b' => {
                    let state = self.pop()?;
                    match self.top()? {
                        Value::Object(o) => o.borrow_mut().state = Some(state),
                        _ => return self.err("BUILD on a non-object"),
                    }
                }
                b'p' => {
                    let l = self.line()?;
                    let k = l.parse().map_err(|_| PickleError { pos: self.pos, msg: format!("PUT {l:?}") })?;
                    self.memo_put(k)?;
                }
                b'q' => {
                    let k = self.u8()? as u64;
                    self.memo_put(k)?;
                }
                b'r' => {
                    let k = self.u32()? as u64;
                    self.memo_put(k)?;
                }
                0x94 => {
                    let k = self.memo.len() as u64;
                    self.memo_put(k)?;
                }
                b'g' => {
                    let l = self.line()?;
                    let k = l.parse().map_err(|_| PickleError { pos: self.pos, msg: format!("GET {l:?}") })?;
                    let v = self.memo_get(k)?;
                    self.stack.push(v);
                }
                b'h' => {
                    let k = self.u8()? as u64;
                    let v = self.memo_get(k)?;
                    self.stack.push(v);
                }
                b'j' => {
                    let k = self.u32()? as u64;
                    let v = self.memo_get(k)?;
                    self.stack.push(v);
                }
                b'P' => {
                    let l = self.line()?.to_string();
                    self.stack.push(Value::PersId(Rc::new(Value::Str(l))));
                }
                b'Q' => {
                    let pid = self.pop()?;
                    self.stack.push(Value::PersId(Rc::new(pid)));
                }
                _ => {
                    self.pos -= 1;
                    return self.err(format!("unsupported opcode 0x{op:02x}"));
                }
            }
        }
    }
}
